"""S3 for tests: moto's server mode (ThreadedMotoServer) on loopback, run in a child process.

Not in-process: some delta-rs calls (DeltaTable.history, is_deltatable) hold the GIL while they wait for
the server, which deadlocks a server thread in the same interpreter. The child keeps moto's in-memory S3
across `stop()` / `start()`, so a test can take the endpoint away (an outage) and bring the same bucket back.
"""

from __future__ import annotations

import socket
import subprocess
import sys
import textwrap

import boto3

_SERVER = textwrap.dedent(
    """
    import logging, sys
    from moto.server import ThreadedMotoServer
    logging.getLogger("werkzeug").setLevel(logging.ERROR)
    port = int(sys.argv[1])
    server = ThreadedMotoServer(ip_address="127.0.0.1", port=port, verbose=False)
    server.start()
    print("started", flush=True)
    for line in sys.stdin:
        command = line.strip()
        if command == "stop":
            server.stop()
            print("stopped", flush=True)
        elif command == "start":
            server = ThreadedMotoServer(ip_address="127.0.0.1", port=port, verbose=False)
            server.start()
            print("started", flush=True)
        elif command == "quit":
            break
    server.stop()
    """
)

REGION = "us-east-1"


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class MotoS3:
    """A moto S3 endpoint on 127.0.0.1:<free port> with `bucket` created."""

    def __init__(self, bucket: str = "so101-history") -> None:
        self.port = _free_port()
        self.endpoint = f"http://127.0.0.1:{self.port}"
        self.bucket = bucket
        self._proc = subprocess.Popen(
            [sys.executable, "-c", _SERVER, str(self.port)],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            text=True,
        )
        self._expect("started")
        self.client().create_bucket(Bucket=bucket)

    def _expect(self, word: str) -> None:
        assert self._proc.stdout is not None
        line = self._proc.stdout.readline().strip()
        if line != word:
            raise RuntimeError(f"moto server said {line!r}, expected {word!r} (exit {self._proc.poll()})")

    def _send(self, command: str) -> None:
        assert self._proc.stdin is not None
        self._proc.stdin.write(command + "\n")
        self._proc.stdin.flush()

    def stop(self) -> None:
        self._send("stop")
        self._expect("stopped")

    def start(self) -> None:
        self._send("start")
        self._expect("started")

    def close(self) -> None:
        if self._proc.poll() is None:
            self._send("quit")
            try:
                self._proc.wait(10)
            except subprocess.TimeoutExpired:
                self._proc.kill()
                self._proc.wait(5)

    def client(self):
        return boto3.client(
            "s3",
            endpoint_url=self.endpoint,
            aws_access_key_id="testing",
            aws_secret_access_key="testing",
            region_name=REGION,
        )

    def storage_options(self) -> dict[str, str]:
        """delta-rs options for this endpoint; short timeouts so an outage fails fast in tests."""
        return {
            "AWS_ENDPOINT_URL": self.endpoint,
            "AWS_ACCESS_KEY_ID": "testing",
            "AWS_SECRET_ACCESS_KEY": "testing",
            "AWS_REGION": REGION,
            "AWS_ALLOW_HTTP": "true",
            "timeout": "5s",
            "connect_timeout": "2s",
            "max_retries": "1",
            "retry_timeout": "3s",
        }
