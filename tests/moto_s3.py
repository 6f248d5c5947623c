"""S3 for tests: moto's server mode (ThreadedMotoServer) on loopback, run in a child process.

Not in-process: some delta-rs calls (DeltaTable.history, is_deltatable) hold the GIL while they wait for
the server, which deadlocks a server thread in the same interpreter. The child keeps moto's in-memory S3
across `stop()` / `start()`, so a test can take the endpoint away (an outage) and bring the same bucket back.
"""

from __future__ import annotations

import subprocess
import sys
import textwrap

import boto3

_SERVER = textwrap.dedent(
    """
    import errno, logging, socket, sys, threading, time
    from moto.moto_server import werkzeug_app as moto
    from werkzeug.serving import make_server
    logging.getLogger("werkzeug").setLevel(logging.ERROR)
    app = moto.DomainDispatcherApplication(moto.create_backend_app)  # its S3 outlives each server below

    def serve(port):
        # Port 0 the first time, read back: a port picked free then bound could be taken between. Again on
        # that port after a stop: freed by this server, it may be another process's for a while (a client
        # connection of another xdist worker's test), so it is tried until free (werkzeug exits on a taken
        # one, hence the socket made here).
        deadline = time.monotonic() + 60
        while True:
            sock = socket.socket()
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            try:
                sock.bind(("127.0.0.1", port))
                break
            except OSError as exc:
                sock.close()
                if exc.errno != errno.EADDRINUSE or time.monotonic() > deadline:
                    raise
                time.sleep(0.2)
        sock.listen(128)
        handler = moto.MotoRequestHandler
        server = make_server("127.0.0.1", 0, app, True, request_handler=handler, fd=sock.fileno())
        threading.Thread(target=server.serve_forever, daemon=True).start()
        return server, sock

    server, sock = serve(0)
    port = sock.getsockname()[1]
    print("started", port, flush=True)
    for line in sys.stdin:
        command = line.strip()
        if command == "stop":
            server.shutdown()
            server.server_close()
            sock.close()
            print("stopped", flush=True)
        elif command == "start":
            server, sock = serve(port)
            print("started", port, flush=True)
        elif command == "quit":
            break
    server.shutdown()
    """
)

REGION = "us-east-1"


class MotoS3:
    """A moto S3 endpoint on 127.0.0.1:<free port> with `bucket` created."""

    def __init__(self, bucket: str = "so101-history") -> None:
        self.bucket = bucket
        self._proc = subprocess.Popen(
            [sys.executable, "-c", _SERVER],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            text=True,
        )
        self.port = int(self._expect("started"))  # the port the server picked
        self.endpoint = f"http://127.0.0.1:{self.port}"
        self.client().create_bucket(Bucket=bucket)

    def _expect(self, word: str) -> str:
        """The rest of the server's next line, which must start with `word`."""
        assert self._proc.stdout is not None
        line = self._proc.stdout.readline().strip()
        said, _, rest = line.partition(" ")
        if said != word:
            raise RuntimeError(f"moto server said {line!r}, expected {word!r} (exit {self._proc.poll()})")
        return rest

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
