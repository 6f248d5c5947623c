"""Settings of the Rerun sink (the `[rerun]` config section); light, so loading a config imports no Rerun.

docs/web.md explains each one. Everything the sink serves listens on the loopback interface only: the twin
host opens no new port, and a person reaches the viewer through an SSM port forward or the DCV desktop.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from pathlib import Path

# The sizes Rerun's server_memory_limit understands: bytes with a binary or decimal unit, or a share of RAM.
_MEMORY_LIMIT = re.compile(r"^\d+(\.\d+)?\s*(B|kB|KB|KiB|MB|MiB|GB|GiB|TB|TiB|%)$")
DEFAULT_GRPC_PORT = 9876  # Rerun's own default, so `rerun --connect` finds it without a URL
DEFAULT_WEB_PORT = 9090


class RerunSettingsError(ValueError):
    """A `[rerun]` value is invalid; the message names the key and the fix."""


@dataclass(frozen=True)
class RerunSettings:
    # Write the stream to this .rrd file ("" = no file). `rerun FILE.rrd` opens it later.
    save: str = ""
    # Serve the stream (gRPC) and the web viewer (HTTP) on 127.0.0.1.
    serve: bool = False
    grpc_port: int = DEFAULT_GRPC_PORT
    web_port: int = DEFAULT_WEB_PORT
    # What the gRPC server keeps for viewers that connect later; the oldest data goes first, the static
    # meshes never. A Rerun size ("512MiB") or a share of RAM ("10%").
    memory_limit: str = "512MiB"
    # Per device, at most this many samples a second go into the stream (the rest are counted as skipped).
    max_rate_hz: float = 20.0
    # ... after a burst of up to burst_s seconds' worth of the cap: a host stall (the MQTT thread starved
    # for seconds, then a normal arm's backlog arriving within milliseconds) must not cost that arm its
    # samples, while a flooding edge is still held to max_rate_hz once its burst is spent. 5 s at 20 Hz is
    # 100 samples: a 10 Hz arm's backlog of a stall up to 10 s.
    burst_s: float = 5.0
    # ... and at most this many samples a second for the whole fleet: past it each device gets an equal share
    # (1,000: 100 arms at 10 Hz pass whole, 200 arms get 5 Hz each). The sink's cost is per sample, on the
    # mirror's interpreter lock: 200 arms at 10 Hz in the soak, on a 2-core host in a slow phase, dropped 12 %
    # of the stream in seconds-long gaps. An even lower rate per arm keeps every arm moving instead.
    max_fleet_rate_hz: float = 1_000.0
    # Samples are sent in columns, one batch per device at most every flush_s: the stream's delay, traded
    # against CPU (docs/web.md has the figures).
    flush_s: float = 0.5
    # ... and at most this many device batches a second in all: a large fleet waits longer instead of
    # costing more CPU and file size, both mostly per batch (100 arms at 20 a second: each arm's samples
    # go every 5 s; up to 10 arms, every flush_s).
    max_batches_per_s: float = 20.0
    # Visual meshes are thinned to this many triangles per arm (a fleet view holds one copy per arm) ...
    mesh_faces_per_arm: int = 50_000
    # ... for the first mesh_detailed_arms arms (the grid's first row, which the layout looks at) and the
    # focus arm; every other arm gets a copy thinned to mesh_faces_far (never more than the detailed one).
    # Static meshes are logged, encoded, written and kept by the stream once per arm: at 100 detailed arms
    # they were most of the .rrd and of the served stream's memory.
    mesh_detailed_arms: int = 10
    mesh_faces_far: int = 10_000
    # Arms in the fleet view stand on a grid this far apart, in order of first appearance.
    fleet_spacing_m: float = 0.6
    # The arm whose joints and servo plots the layout opens on ("" = the first arm seen).
    focus_device: str = ""
    # The sink's queue: samples waiting for the Rerun thread (the oldest are dropped beyond it).
    max_pending: int = 10_000
    # The saved .rrd rotates once it reaches save_max_mb or is save_max_age_s old (it grows about 1.5 MB a
    # second at 200 arms); the rotated files beside it are kept within save_budget_mb, the oldest deleted
    # first (docs/web.md).
    save_max_mb: float = 512.0
    save_max_age_s: float = 3600.0
    save_budget_mb: float = 4096.0

    @property
    def enabled(self) -> bool:
        return bool(self.save) or self.serve

    def validate(self) -> RerunSettings:
        """Raise RerunSettingsError naming the first bad key; returns self."""
        for key in ("grpc_port", "web_port"):
            port = getattr(self, key)
            if not 0 <= port <= 65535:
                raise RerunSettingsError(f"rerun.{key} = {port} is outside 0..65535 (0 picks a free port)")
        if self.serve and self.grpc_port != 0 and self.grpc_port == self.web_port:
            raise RerunSettingsError(
                f"rerun.grpc_port and rerun.web_port are both {self.grpc_port}; give them different ports"
            )
        if not _MEMORY_LIMIT.match(self.memory_limit.strip()):
            raise RerunSettingsError(
                f"rerun.memory_limit = {self.memory_limit!r} is not a size; "
                "use e.g. '512MiB', '2GiB' or '10%'"
            )
        for key in ("max_rate_hz", "max_fleet_rate_hz", "flush_s", "max_batches_per_s", "fleet_spacing_m"):
            value = getattr(self, key)
            if not (math.isfinite(value) and value > 0):
                raise RerunSettingsError(f"rerun.{key} = {value!r} must be a number greater than 0")
        if not (math.isfinite(self.burst_s) and self.burst_s > 0):
            raise RerunSettingsError(
                f"rerun.burst_s = {self.burst_s!r} must be a number of seconds greater than 0: how much of "
                "max_rate_hz a device may send at once after a pause (e.g. burst_s = 5.0)"
            )
        if self.flush_s > 10:
            raise RerunSettingsError(
                f"rerun.flush_s = {self.flush_s} delays the stream by that long; use at most 10 s"
            )
        for key in ("mesh_faces_per_arm", "mesh_faces_far"):
            faces = getattr(self, key)
            if faces < 100:
                raise RerunSettingsError(f"rerun.{key} = {faces} leaves no arm to see; use at least 100")
        if self.mesh_detailed_arms < 0:
            raise RerunSettingsError(
                f"rerun.mesh_detailed_arms = {self.mesh_detailed_arms} must be 0 or more "
                "(0: only the focus arm is detailed)"
            )
        if self.max_pending < 1:
            raise RerunSettingsError(f"rerun.max_pending = {self.max_pending} must be at least 1")
        for key in ("save_max_mb", "save_max_age_s", "save_budget_mb"):
            value = getattr(self, key)
            if not (math.isfinite(value) and value > 0):
                raise RerunSettingsError(f"rerun.{key} = {value!r} must be a number greater than 0")
        if self.save_budget_mb < self.save_max_mb:
            raise RerunSettingsError(
                f"rerun.save_budget_mb = {self.save_budget_mb:g} is below save_max_mb = "
                f"{self.save_max_mb:g}; the budget must hold at least one whole file"
            )
        self._validate_save()
        return self

    def _validate_save(self) -> None:
        if not self.save:
            return
        path = Path(self.save)
        if path.suffix != ".rrd":
            raise RerunSettingsError(
                f"rerun.save = {self.save!r} must name a .rrd file (Rerun's recording format), e.g. twin.rrd"
            )
        if path.is_dir():
            raise RerunSettingsError(f"rerun.save = {self.save!r} is a directory; give a file name")
