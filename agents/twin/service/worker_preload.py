"""What the workers' fork server imports before it forks any worker (workerstart.WORKER_PRELOAD): the mirror
with NumPy and MuJoCo, and the agent's model (`[twin] model`, else the bundled scene) compiled meanwhile,
so each worker, at start or again after a crash, begins with both.

- MuJoCo binds no OpenGL backend here: a worker mirrors and never renders. MuJoCo picks its backend when it
  is first imported, from MUJOCO_GL, and binding one costs 0.1-0.2 s (GLFW checks its library's version in
  a Python subprocess; EGL loads the driver). Only the fork server and its workers run with this setting:
  the agent's own process keeps its environment, so an in-process mirror beside a renderer still renders.
- MuJoCo compiles the model without holding the GIL, so the compile (about 0.15 s) runs on a thread while
  the rest of the mirror imports, and each worker takes the result (twin.robot.model.precompile) instead of
  compiling after its fork. The thread ends before this import does: nothing is forked mid-compile.

Measured in docs/performance.md ("Footprint").
"""

from __future__ import annotations

import os
import threading
from pathlib import Path

from twin.service.workerstart import WORKER_MODEL_ENV

os.environ["MUJOCO_GL"] = "disable"

# MuJoCo (imported by the model) only now that MUJOCO_GL is set.
from twin.robot.model import default_model_path, precompile

# Taken out of the environment: the workers forked from here have no use for it.
_model = os.environ.pop(WORKER_MODEL_ENV, "")
_compile = threading.Thread(
    target=precompile, args=(Path(_model) if _model else default_model_path(),), name="twin-precompile"
)
_compile.start()
import twin.service.mirror  # noqa: E402 - the worker's mirror, while the model compiles
import twin.service.shards  # noqa: E402, F401 - the worker's entry point (worker_main)

_compile.join()
