"""The workers' fork server preload (twin.service.worker_preload), run in a process of its own as the fork
server runs it: MuJoCo binds no OpenGL backend, the mirror is imported, and the bundled model is compiled
before the import returns, for each worker forked afterwards to take."""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap

from twin.rig.local import child_env
from twin.service.workerstart import WORKER_PRELOAD

PROBE = textwrap.dedent(
    """
    import json, os, sys, threading
    for name in sys.argv[1:]:
        __import__(name)
    import mujoco.rendering.classic.gl_context as gl
    from twin.robot import model
    from twin.robot.model import RobotModel, default_model_path

    compiled = model._PRECOMPILED.get(default_model_path().resolve())
    pid = os.fork()
    if pid == 0:  # as a worker forked from the server: its first load takes the compiled model
        os._exit(0 if compiled is not None and RobotModel.load().model is compiled else 3)
    _, status = os.waitpid(pid, 0)
    print(json.dumps({
        "env": os.environ.get("MUJOCO_GL"),
        "bound": gl._MUJOCO_GL,
        "mirror": "twin.service.mirror" in sys.modules and "twin.service.shards" in sys.modules,
        "threads": [t.name for t in threading.enumerate()],
        "worker_exit": os.waitstatus_to_exitcode(status),
    }))
    """
)


def test_the_preload_binds_no_gl_imports_the_mirror_and_leaves_the_model_compiled() -> None:
    env = child_env()
    env["MUJOCO_GL"] = "egl"  # as the host's agent service sets it (userdata/install-agent.sh)
    done = subprocess.run(
        [sys.executable, "-c", PROBE, *WORKER_PRELOAD],
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert done.returncode == 0, done.stderr
    got = json.loads(done.stdout.strip().splitlines()[-1])
    assert got["env"] == got["bound"] == "disable"
    assert got["mirror"] is True
    assert got["threads"] == ["MainThread"], "the compile must end before the server forks a worker"
    assert got["worker_exit"] == 0, "the forked worker did not take the precompiled model"
