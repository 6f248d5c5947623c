"""The workers' fork server preload (twin.service.worker_preload), run in a process of its own as the fork
server runs it: MuJoCo binds no OpenGL backend, the mirror is imported, and the agent's model (the bundled
one unless `[twin] model` names another) is compiled before the import returns, for each worker forked
afterwards to take."""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap
from pathlib import Path
from typing import Any

import pytest
from conftest import copy_bundled_scene
from twin.rig.local import child_env
from twin.service.workerstart import WORKER_MODEL_ENV, WORKER_PRELOAD

PROBE = textwrap.dedent(
    """
    import json, os, sys, threading
    from pathlib import Path
    for name in sys.argv[1:]:
        __import__(name)
    import mujoco.rendering.classic.gl_context as gl
    from twin.robot import model
    from twin.robot.model import RobotModel, default_model_path

    wanted = os.environ.get("PROBE_MODEL")
    path = wanted or default_model_path()
    compiled = model._PRECOMPILED.get(Path(path).resolve())
    pid = os.fork()
    if pid == 0:  # as a worker forked from the server: its first load takes the compiled model
        os._exit(0 if compiled is not None and RobotModel.load(wanted).model is compiled else 3)
    _, status = os.waitpid(pid, 0)
    print(json.dumps({
        "env": os.environ.get("MUJOCO_GL"),
        "bound": gl._MUJOCO_GL,
        "mirror": "twin.service.mirror" in sys.modules and "twin.service.shards" in sys.modules,
        "threads": [t.name for t in threading.enumerate()],
        "worker_exit": os.waitstatus_to_exitcode(status),
        "compiled": [str(p) for p in model._PRECOMPILED],
        "passed_on": os.environ.get("TWIN_WORKER_MODEL"),
    }))
    """
)


def run_script(script: str, args: list[str], env: dict[str, str], cwd: Path | None = None) -> dict[str, Any]:
    """`script` in a Python process of its own; what it printed last, as JSON."""
    done = subprocess.run(
        [sys.executable, "-c", script, *args],
        env=env,
        cwd=cwd,
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert done.returncode == 0, done.stderr
    return json.loads(done.stdout.strip().splitlines()[-1])


def run_probe(env: dict[str, str]) -> dict[str, Any]:
    """PROBE: the preload imported as the fork server imports it."""
    return run_script(PROBE, list(WORKER_PRELOAD), env)


def test_the_preload_binds_no_gl_imports_the_mirror_and_leaves_the_model_compiled() -> None:
    env = child_env()
    env["MUJOCO_GL"] = "egl"  # as the host's agent service sets it (userdata/install-agent.sh)
    env.pop(WORKER_MODEL_ENV, None)
    got = run_probe(env)
    assert got["env"] == got["bound"] == "disable"
    assert got["mirror"] is True
    assert got["threads"] == ["MainThread"], "the compile must end before the server forks a worker"
    assert got["worker_exit"] == 0, "the forked worker did not take the precompiled model"


def test_the_preload_compiles_the_configured_model_instead_of_the_bundled_one(tmp_path: Path) -> None:
    # `[twin] model` names another MJCF: that one is compiled ahead, and the bundled scene is not.
    scene = copy_bundled_scene(tmp_path)
    env = child_env()
    env[WORKER_MODEL_ENV] = env["PROBE_MODEL"] = str(scene)
    got = run_probe(env)
    assert got["compiled"] == [str(scene.resolve())]
    assert got["worker_exit"] == 0, "the forked worker did not take the precompiled model"
    assert got["passed_on"] is None, "the workers need not inherit the variable"


START = textwrap.dedent(
    """
    import json, multiprocessing.forkserver, os, pathlib, sys
    from twin.rig.local import wait_until
    from twin.service.workerstart import WORKER_MODEL_ENV, start_fork_server

    start_fork_server(sys.argv[1])
    proc = f"/proc/{multiprocessing.forkserver._forkserver._forkserver_pid}"
    # Until the server has exec'd: before that, /proc shows the spawning fork, with this script's command line
    # and the environment this process started with. (Split, so this script's own text does not match.)
    server_main = b"from multiprocessing.forkserver " + b"import main"
    wait_until(lambda: server_main in pathlib.Path(f"{proc}/cmdline").read_bytes(), 60, "the server's exec")
    with open(f"{proc}/environ", "rb") as env:
        server = dict(v.decode().split("=", 1) for v in env.read().split(b"\\0") if b"=" in v)
    print(json.dumps({"server": server.get(WORKER_MODEL_ENV), "agent": os.environ.get(WORKER_MODEL_ENV)}))
    """
)


@pytest.mark.parametrize("model", ["robots/arm.xml", ""])
def test_start_fork_server_passes_the_model_to_the_server_only(model: str, tmp_path: Path) -> None:
    # The fork server's environment at its start carries the model (made absolute: a relative
    # `[twin] model` is read from the agent's working directory), the agent's own environment does not.
    env = child_env()
    env.pop(WORKER_MODEL_ENV, None)
    got = run_script(START, [model], env, cwd=tmp_path)
    assert got == {"server": str(tmp_path / model) if model else "", "agent": None}
