"""Settings of `twin view`: one object, built by the command from its flags."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from twin.service.config import DEFAULT_AGENT_URL


@dataclass(frozen=True)
class ViewerConfig:
    """Settings of `twin view` (one object, built by the command from its flags)."""

    agent_url: str = DEFAULT_AGENT_URL
    device: str | None = None
    model_path: str | Path | None = None
    fps: float = 60.0
    smoothing: str = "predict"
    show_ui: bool = False
    camera: str | None = None
    # A stream that stays silent this long is dead (the agent streams at tens of Hz).
    read_timeout_s: float = 3.0
    retry_s: float = 0.5
    max_retry_s: float = 5.0
    poll_hz: float = 20.0
    # While polling because the stream failed, the stream is retried this often.
    stream_retry_s: float = 15.0

    def __post_init__(self) -> None:
        if not self.agent_url.startswith(("http://", "https://")):
            raise ValueError(f"--agent {self.agent_url!r} must be an http(s) URL, e.g. {DEFAULT_AGENT_URL}")
        if not 1.0 <= self.fps <= 240.0:
            raise ValueError(f"--fps {self.fps} must be between 1 and 240")
