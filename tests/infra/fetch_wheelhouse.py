"""Download into a folder, by hash, the wheels the installer tests install offline (`make setup` runs it).

The host installs from requirements/host.txt with --require-hashes; the tests do the same with a lock of a few
of its packages (tests/infra/hostsim.py): the build backend the agent is built with (setuptools, wheel) and
Pillow, which the host's screen check runs on. Their entries are taken from host.txt as they are, hashes
included, so pip refuses any file that is not the locked one.

    python tests/infra/fetch_wheelhouse.py requirements/host.txt .wheelhouse setuptools wheel pillow
"""

from __future__ import annotations

import re
import subprocess
import sys
import tempfile
from pathlib import Path

_ENTRY = re.compile(r"^([A-Za-z0-9][A-Za-z0-9._-]*)==")


def canonical(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


def entries(lock: str, names: set[str]) -> str:
    """The lock's entries (a `name==version ... \\` line and its hash lines) for `names`."""
    blocks = re.split(r"\n(?=\S)", lock)
    chosen = [b for b in blocks if (m := _ENTRY.match(b)) and canonical(m.group(1)) in names]
    found = {canonical(_ENTRY.match(b).group(1)) for b in chosen}  # type: ignore[union-attr]
    if found != names:
        raise SystemExit(f"{sorted(names - found)} not in the lock")
    return "\n".join(chosen) + "\n"


def main(argv: list[str]) -> int:
    lock, target, *names = argv
    wanted = entries(Path(lock).read_text(), {canonical(n) for n in names})
    with tempfile.NamedTemporaryFile("w", suffix=".txt") as requirements:
        requirements.write(wanted)
        requirements.flush()
        command = [sys.executable, "-m", "pip", "--disable-pip-version-check", "-q", "download"]
        command += ["--require-hashes", "--no-deps", "--only-binary=:all:", "-d", target]
        command += ["-r", requirements.name]
        return subprocess.run(command, check=False).returncode


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
