"""The optional outputs an agent config turns on, built for `AgentService(config, sinks=...)`.

The USD recording is the service's own sink (`[twin] record_dir`); every other output is an extra sink that
the entry points (`twin run`, `twin web`, `twin demo`) build here from the same config, so each is set up in
one place: the ROS 2 bridge (`[ros2]`, docs/ros2.md) and the Rerun sink (`[rerun]`, docs/web.md).
"""

from __future__ import annotations

import logging

from twin.output.sinks import TwinSink
from twin.robot.model import ModelError, RobotModel
from twin.service.config import AgentConfig, ConfigError

log = logging.getLogger(__name__)


def unwritable_fix(exc: BaseException) -> str:
    """What to do about `exc` when it is a path the agent cannot make or write (`--record-dir` on a read-only
    disk, a state file under a file): the OS's words alone name no way out. "" for any other error."""
    if not isinstance(exc, OSError) or not exc.filename:
        return ""
    return (
        f"; the agent must be able to write {exc.filename}: make that place writable by the user it runs as "
        "(with free space), or point the option or setting that names it elsewhere"
    )


def configured_sinks(config: AgentConfig, robot: RobotModel | None = None) -> list[TwinSink]:
    """The extra sinks `config` asks for, started (a served Rerun stream listens once this returns).

    `robot` is the model the sinks pose; None loads the config's (`[twin] model`). Raises ConfigError for a
    model that cannot be loaded, OSError when a sink cannot open what it serves or writes (a port in use).
    The caller owns the sinks: `AgentService.stop()` closes them, or `close_sinks` when the service never
    started.
    """
    sinks: list[TwinSink] = []
    if config.ros2.enabled:
        # cyclonedds loads only with the bridge on (the ros2 extra).
        from twin.output.ros2 import Ros2Error, open_ros2_sink  # noqa: PLC0415

        try:
            sinks.append(open_ros2_sink(config.ros2))
        except Ros2Error as exc:
            raise ConfigError(str(exc)) from exc
    if config.rerun.enabled:
        # rerun and pyarrow load only when the stream is on: `twin run` without it does not pay for them.
        from twin.output.rerun_sink import RerunSink  # noqa: PLC0415

        if robot is None:
            try:
                robot = RobotModel.load(config.twin.model or None)
            except ModelError as exc:
                close_sinks(sinks)
                raise ConfigError(f"twin.model = {config.twin.model!r}: {exc}") from exc
        try:
            sink = RerunSink(robot, config.rerun)
        except BaseException:
            close_sinks(sinks)  # the ROS 2 bridge, if it started, holds DDS threads
            raise
        sinks.append(sink)
        if sink.viewer_url:
            log.info(
                "rerun web viewer serving",
                extra={"url": sink.viewer_url, "grpc": sink.grpc_url, "rrd": str(sink.save_path or "")},
            )
        elif sink.save_path:
            log.info("rerun recording", extra={"rrd": str(sink.save_path)})
    return sinks


def close_sinks(sinks: list[TwinSink], timeout: float = 5.0) -> None:
    """Close sinks no service took over (start-up failed before the service existed)."""
    for sink in sinks:
        try:
            sink.close(timeout)
        except Exception:
            log.exception("closing sink %s failed", sink.name)
