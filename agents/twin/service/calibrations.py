"""Each arm's own LeRobot calibration, kept in a store the agent watches: a directory or s3://bucket/prefix.

A real SO-101 is calibrated once with LeRobot (`lerobot-calibrate`), which writes one JSON file per arm
(twin.robot.calibration reads it). The twin needs that file to turn an arm's raw positions (ticks, or
range100) into the right angles, and five arms have five different files. The store holds one object per arm,
named for its device id: `<store>/<device>.json`. `twin calibration push ARM FILE` puts one there (on AWS the
stack's bucket, prefix `calibration/`: the CalibrationUri output), and the agent picks it up without a
redeploy or a restart:

- `CalibrationWatcher` lists the store every `telemetry.calibration_poll_s` (one LIST call for the whole
  fleet: S3 returns each object's ETag, a directory each file's modification time and size) and reads only
  the files that are new or changed since the last poll; a file that is removed takes its arm back to the
  config's calibration, or the nominal SO-101's when the config has none.
- A file that is not a valid SO-101 calibration is refused with the reason (logged, and kept in
  `CalibrationBook.problems`); the arm keeps the calibration it had, so a bad upload never moves its twin.
  An arm with none to keep (the agent started with the bad file there) is held: its messages are refused as
  `calibration_refused` rather than decoded with the config's calibration, another arm's (unless they are
  in degrees, which use none). The kept file of a refused arm is read too, once a version, to offer
  `restore` only when it is valid.
- The agent hands each new book to its mirrors (AgentService), whose decoders swap the arm's table in whole.

Listing and reading go through `CalibrationStore`, one for a directory and one for S3 (boto3, built lazily,
or injected by tests).
"""

from __future__ import annotations

import dataclasses
import logging
import os
import shlex
import threading
import time
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

from twin.core.aws import region_or_env
from twin.core.locations import location_problem
from twin.core.topics import POLICY_DEVICE_ID_RULE, policy_device_id_problem
from twin.core.units import Units
from twin.robot.calibration import MAX_FILE_BYTES, Calibration, parse_calibration
from twin.service.persist import is_temporary, write_atomically

log = logging.getLogger(__name__)

SUFFIX = ".json"
# The calibration a push or rm replaced, kept beside the arm's own under this name's ending, one per arm:
# the store may be a bucket without versioning (the stack's, as Delta's files want), and a calibration is an
# hour with the arm. Not `.json`, so no listing takes it for an arm's.
KEPT_SUFFIX = ".json.previous"
DEFAULT_POLL_S = 30.0
# A directory store's temporary file older than this is a cut-short write's (a push takes milliseconds).
LEFTOVER_AGE_S = 600.0
# The agent setting that names the store, as the console names it.
SETTING = "[telemetry] calibrations"
# The prefix the stack keeps the calibrations under in its bucket (stacks/history_bucket.py): an agent that
# reads s3://<bucket>/calibration is the twin host, whose store a plain `twin calibration push` writes to
# (the stack's CalibrationUri output).
STACK_PREFIX = "calibration"


class CalibrationStoreError(Exception):
    """The store could not be listed or read (no access, no network, no such bucket or directory)."""


class StoreCredentialsError(CalibrationStoreError):
    """An S3 store could not be reached because this machine has no AWS credentials (the message says how to
    give it some): a setup problem, which `twin calibration` reports apart from the store's own errors."""


class CalibrationStore(Protocol):
    """Where the arms' calibration files are kept."""

    @property
    def uri(self) -> str: ...

    def listing(self) -> dict[str, str]:
        """Device id -> a version that changes whenever its file does (ETag, or mtime), ending in
        `:<size in bytes>` (`twin calibration push` reads only same-sized files when it looks for copies)."""
        ...

    def read(self, device: str) -> bytes: ...

    def write(self, device: str, data: bytes) -> str:
        """Store `data` as the device's file; returns where it went."""
        ...

    def delete(self, device: str) -> bool:
        """Remove the device's file; False when there was none."""
        ...

    def uri_of(self, device: str) -> str: ...

    def read_kept(self, device: str) -> bytes | None:
        """The calibration the device's last push or rm replaced (KEPT_SUFFIX), None when none is kept."""
        ...

    def scan(self) -> StoreScan:
        """One listing of the store: the arms' calibrations, the kept ones, and the files that look like
        calibrations but are named for no device id (which no arm reads)."""
        ...

    def write_kept(self, device: str, data: bytes) -> str:
        """Keep `data` as the calibration the device's file replaced; returns where it went."""
        ...

    def delete_kept(self, device: str) -> None:
        """Forget the kept calibration, if any."""
        ...


# A store keeps calibrations only for the device ids a deployment may list (twin.core.topics, the stricter
# of its two rules), a directory as much as the stack's bucket: the ids are typed at a shell and become file
# names and S3 keys, and a file pushed to a laptop's directory can then go to the stack's store as it is.


@dataclass(frozen=True)
class StoreScan:
    """What one listing of a store found (`CalibrationStore.scan`)."""

    calibrations: dict[str, str]  # device id -> a version that changes whenever its file does
    kept: dict[str, str]  # device id -> the version of its kept calibration (KEPT_SUFFIX)
    # Names ending in `.json` (or KEPT_SUFFIX) that name no device id: `arm 9.json`, `ARM-001.JSON`. No arm
    # reads them, so a person who copied a file in by hand is told rather than left to wonder.
    ignored: tuple[str, ...]
    # A directory store whose directory does not exist (yet, or a mistyped path): it holds nothing.
    missing: bool = False


def scan_of(names: Iterable[tuple[str, str]]) -> StoreScan:
    """A store's (file name, version) pairs, sorted into a StoreScan."""
    calibrations: dict[str, str] = {}
    kept: dict[str, str] = {}
    ignored: list[str] = []
    for name, version in names:
        device = device_of(name)
        if device is not None:
            calibrations[device] = version
            continue
        device = device_of(name, KEPT_SUFFIX)
        if device is not None:
            kept[device] = version
        elif name.lower().endswith((SUFFIX, KEPT_SUFFIX)):
            ignored.append(name)
    return StoreScan(calibrations, kept, tuple(sorted(ignored)))


def device_of(name: str, suffix: str = SUFFIX) -> str | None:
    """The device id a file name in the store stands for, or None when it names no device; with KEPT_SUFFIX,
    the device whose kept calibration it is."""
    if not name.endswith(suffix):
        return None
    device = name[: -len(suffix)]
    return device if policy_device_id_problem(device) is None else None


def ignored_fix(name: str, push: str) -> str:
    """Why no arm reads `name` (a file in the store that StoreScan.ignored lists) and what to do about it;
    `push` is the push command that reaches this store."""
    if name.startswith("."):
        # A hidden file: an editor's backup or swap, a copy cut short, a desktop's metadata (`._arm-1.json`).
        # Taking it for an arm's could move that arm's twin with an old or half-written file.
        plain = name.lstrip(".")
        # Not for macOS's `._<name>` files: they hold the named file's metadata, never a calibration.
        to = f" ({plain} here)" if device_of(plain) is not None and not name.startswith("._") else ""
        return (
            "its name starts with '.', so it is a hidden file (an editor's, a cut-short copy's), never an "
            f"arm's calibration: if it is one, rename it to <device id>.json{to} or push it (`{push}`); "
            "else remove it"
        )
    return (
        f"a calibration is named <device id>.json and a device id here is {POLICY_DEVICE_ID_RULE}. If it is "
        f"the file of an arm whose id is such, push it under that id (`{push}`); an arm whose id is not "
        "cannot have a calibration of its own: rename the arm on the edge"
    )


def check_device(device: str) -> None:
    """ValueError naming the rule when `device` cannot be an arm's file name in a store."""
    if policy_device_id_problem(device) is not None:
        raise ValueError(f"{device!r} is not a device id: a device id is {POLICY_DEVICE_ID_RULE}")


@dataclass(frozen=True)
class DirectoryStore:
    """A directory of `<device>.json` files (a laptop's agent, the tests). Its path is made absolute: an
    agent keeps watching the directory it started with, the one its console tells people to push to
    (push_hint), whatever its working directory is later."""

    path: Path

    def __post_init__(self) -> None:
        object.__setattr__(self, "path", self.path.absolute())

    @property
    def uri(self) -> str:
        return str(self.path)

    def listing(self) -> dict[str, str]:
        return self.scan().calibrations

    def scan(self) -> StoreScan:
        """The files' versions are their modification time and size."""
        try:
            entries = list(os.scandir(self.path))
        except FileNotFoundError:
            return dataclasses.replace(scan_of(()), missing=True)
        except NotADirectoryError as exc:
            if not self.path.is_file():
                # A name above it is the file (`--store agent.toml/cal`): this path is none, nor a directory.
                raise CalibrationStoreError(f"cannot list {self.path}: {exc}") from exc
            # `--store` given a calibration file (or the agent's config) for the directory it belongs in.
            raise CalibrationStoreError(
                f"{self.path} is a file, not a store: give the directory of the agent's [telemetry] "
                "calibrations, which holds one <device>.json per arm"
            ) from None
        except OSError as exc:
            raise CalibrationStoreError(f"cannot list {self.path}: {exc}") from exc
        files = []
        now = time.time()
        for entry in entries:
            try:
                if not entry.is_file():
                    continue
                st = entry.stat()
            except FileNotFoundError:
                # Gone since the listing: a push's temporary file renamed into place (the next poll reads
                # the arm's file), or an rm. It raised past the poll, which then skipped the whole fleet.
                continue
            except OSError as exc:
                raise CalibrationStoreError(f"cannot read {entry.path}'s size: {exc}") from exc
            if is_temporary(entry.name):
                if now - st.st_mtime > LEFTOVER_AGE_S:
                    self._remove_leftover(entry.path)
                continue
            files.append((entry.name, f"{st.st_mtime_ns}:{st.st_size}"))
        return scan_of(files)

    def _remove_leftover(self, path: str) -> None:
        """A push killed between its temporary file and the rename leaves that file, as large as a
        calibration, and nothing else would ever remove it."""
        try:
            os.unlink(path)
        except OSError as exc:
            log.debug("leftover %s not removed: %s", path, exc)
            return
        log.info("removed %s, left by a calibration write that was cut short", path, extra={"path": path})

    def read(self, device: str) -> bytes:
        found = self._get(f"{device}{SUFFIX}", missing_ok=False)
        assert found is not None  # a missing file raised
        return found

    def write(self, device: str, data: bytes) -> str:
        check_device(device)
        return self._put(f"{device}{SUFFIX}", data)

    def delete(self, device: str) -> bool:
        try:
            (self.path / f"{device}{SUFFIX}").unlink()
        except FileNotFoundError:
            return False
        except OSError as exc:
            raise CalibrationStoreError(f"cannot delete {self.path / f'{device}{SUFFIX}'}: {exc}") from exc
        return True

    def uri_of(self, device: str) -> str:
        return str(self.path / f"{device}{SUFFIX}")

    def read_kept(self, device: str) -> bytes | None:
        return self._get(f"{device}{KEPT_SUFFIX}", missing_ok=True)

    def write_kept(self, device: str, data: bytes) -> str:
        check_device(device)
        return self._put(f"{device}{KEPT_SUFFIX}", data)

    def delete_kept(self, device: str) -> None:
        path = self.path / f"{device}{KEPT_SUFFIX}"
        try:
            path.unlink(missing_ok=True)
        except OSError as exc:
            raise CalibrationStoreError(f"cannot delete {path}: {exc}") from exc

    def _get(self, name: str, *, missing_ok: bool) -> bytes | None:
        path = self.path / name
        try:
            with path.open("rb") as fh:
                return fh.read(MAX_FILE_BYTES + 1)
        except OSError as exc:
            if missing_ok and isinstance(exc, FileNotFoundError):
                return None
            raise CalibrationStoreError(f"cannot read {path}: {exc}") from exc

    def _put(self, name: str, data: bytes) -> str:
        path = self.path / name
        try:
            # A rename, so the watcher never reads half a file, after an fsync, so a power cut cannot leave
            # an arm's calibration empty; a temporary file of its own, so two pushes cannot mix.
            write_atomically(path, data)
        except OSError as exc:
            # A store's error, as S3's are: `restore` then saves the calibration only it still holds.
            raise CalibrationStoreError(f"cannot write to {path}: {exc}") from exc
        return str(path)


@dataclass
class S3Store:
    """`s3://bucket/prefix/<device>.json`; the client is built on first use unless given."""

    bucket: str
    prefix: str
    region: str = ""
    client: Any = None

    @property
    def uri(self) -> str:
        return f"s3://{self.bucket}/{self.prefix}" if self.prefix else f"s3://{self.bucket}"

    def _s3(self) -> Any:
        if self.client is None:
            import boto3  # noqa: PLC0415 - loading a config must not pay for boto3
            from botocore.config import Config  # noqa: PLC0415

            self.client = boto3.client(
                "s3",
                region_name=region_or_env(self.region),
                config=Config(connect_timeout=5, read_timeout=10, retries={"max_attempts": 3}),
            )
        return self.client

    def _key(self, device: str, suffix: str = SUFFIX) -> str:
        return f"{self.prefix}/{device}{suffix}" if self.prefix else f"{device}{suffix}"

    def _call(self, action: str, fn: Callable[[], Any]) -> Any:
        from botocore.exceptions import (  # noqa: PLC0415
            BotoCoreError,
            ClientError,
            NoCredentialsError,
            PartialCredentialsError,
        )

        try:
            return fn()
        except (NoCredentialsError, PartialCredentialsError) as exc:
            # botocore's "Unable to locate credentials" names no way to give this machine some.
            raise StoreCredentialsError(
                f"cannot {action} {self.uri}: {exc}: run `aws configure` or `aws sso login`, set "
                "AWS_PROFILE, or export AWS_ACCESS_KEY_ID and AWS_SECRET_ACCESS_KEY"
            ) from exc
        except ClientError as exc:
            error = exc.response.get("Error", {})
            raise CalibrationStoreError(
                f"cannot {action} {self.uri}: {error.get('Code')}: {error.get('Message')}"
            ) from exc
        except BotoCoreError as exc:
            raise CalibrationStoreError(f"cannot {action} {self.uri}: {exc}") from exc

    def listing(self) -> dict[str, str]:
        return self.scan().calibrations

    def scan(self) -> StoreScan:
        """The objects right under the prefix (one LIST, paged); their versions are the ETag and size."""
        start = f"{self.prefix}/" if self.prefix else ""

        def pages() -> list[dict[str, Any]]:
            paginator = self._s3().get_paginator("list_objects_v2")
            return list(paginator.paginate(Bucket=self.bucket, Prefix=start))

        objects = []
        for page in self._call("list", pages):
            for obj in page.get("Contents", []):
                name = obj["Key"][len(start) :]
                if "/" not in name:
                    objects.append((name, str(obj.get("ETag", "")) + f":{obj.get('Size', 0)}"))
        return scan_of(objects)

    def read(self, device: str) -> bytes:
        found = self._get(self._key(device), missing_ok=False)
        assert found is not None  # a missing object raised
        return found

    def write(self, device: str, data: bytes) -> str:
        check_device(device)
        return self._put(self._key(device), data)

    def delete(self, device: str) -> bool:
        if device not in self.listing():
            return False
        self._call("delete from", lambda: self._s3().delete_object(Bucket=self.bucket, Key=self._key(device)))
        return True

    def uri_of(self, device: str) -> str:
        return f"s3://{self.bucket}/{self._key(device)}"

    def read_kept(self, device: str) -> bytes | None:
        return self._get(self._key(device, KEPT_SUFFIX), missing_ok=True)

    def write_kept(self, device: str, data: bytes) -> str:
        check_device(device)
        return self._put(self._key(device, KEPT_SUFFIX), data)

    def delete_kept(self, device: str) -> None:
        key = self._key(device, KEPT_SUFFIX)
        # Deleting a key that is not there is no error in S3.
        self._call("delete from", lambda: self._s3().delete_object(Bucket=self.bucket, Key=key))

    def _get(self, key: str, *, missing_ok: bool) -> bytes | None:
        from botocore.exceptions import ClientError  # noqa: PLC0415

        def get() -> bytes | None:
            try:
                body = self._s3().get_object(Bucket=self.bucket, Key=key)["Body"]
            except ClientError as exc:
                if missing_ok and exc.response.get("Error", {}).get("Code") in ("NoSuchKey", "404"):
                    return None
                raise
            try:
                return bytes(body.read(MAX_FILE_BYTES + 1))
            finally:
                body.close()

        found = self._call("read", get)
        return None if found is None else bytes(found)

    def _put(self, key: str, data: bytes) -> str:
        self._call(
            "write to",
            lambda: self._s3().put_object(
                Bucket=self.bucket, Key=key, Body=data, ContentType="application/json"
            ),
        )
        return f"s3://{self.bucket}/{key}"


def open_store(uri: str, *, region: str = "", s3_client: Any = None) -> CalibrationStore:
    """The store at `uri`: s3://bucket[/prefix], file:///dir or a directory path."""
    uri = uri.strip()
    problem = location_problem(uri)
    if problem:
        raise ValueError(f"{uri!r} {problem}; e.g. s3://<bucket>/calibration or a directory")
    if uri.startswith("s3://"):
        bucket, _, prefix = uri.removeprefix("s3://").partition("/")
        return S3Store(bucket, prefix.strip("/"), region, s3_client)
    return DirectoryStore(Path(uri.removeprefix("file://")).expanduser())


def store_location(store: CalibrationStore | None) -> str:
    """Where an agent reads the arms' calibrations from, as a `--store` that means the same from any working
    directory: s3://bucket/prefix or an absolute path; "" when it reads none."""
    return "" if store is None else store.uri


@dataclass(frozen=True)
class PushHint:
    """How to give an arm a calibration that the agent serving the console reads (its Arm page says it)."""

    store: str  # store_location of the agent's store ("" for none)
    command: str  # the command to run, FILE standing for the arm's LeRobot calibration ("" when none can be)
    text: str  # the sentence the page shows, the command in it


def is_stack_store(store: str) -> bool:
    """Whether `store` (store_location) is the deployed stack's bucket, plain `twin calibration`'s default."""
    return store.startswith("s3://") and store.removeprefix("s3://").partition("/")[2] == STACK_PREFIX


def store_option(store: str) -> str:
    """The option `twin calibration` needs to reach `store` (store_location), with its leading space: none
    for the deployed stack's bucket (the command's default), `--store` for any other."""
    if not store or is_stack_store(store):
        return ""
    return f" --store {shlex.quote(store)}"


def refused_effect(*, kept: bool, units: Units) -> str:
    """What a refused file does to its arm, as the log and the Events page say it (`kept`: the arm has a
    calibration from the store to keep)."""
    if units is Units.DEGREES:
        return "which changes nothing: the arms publish degrees, which use no calibration"
    # At a start the arm had none from the store: the config's is another arm's, so its twin holds still (its
    # messages refused as calibration_refused) until a good one comes. While it runs the arm keeps the one
    # it had, but only until the agent starts again, which the log did not say.
    effect = (
        "it keeps the one it had until the agent starts again, which holds its twin still"
        if kept
        else "its twin holds still until a good file is pushed or the file removed"
    )
    return effect + (" (unless it publishes degrees, which use none)" if units is Units.AUTO else "")


def missing_store_notice(store: str, fallback: str) -> str:
    """What the agent warns of, and `twin config check` notes, for a directory store that is not there;
    `fallback` the config's [telemetry] calibration ("": none set), as for without_own."""
    return (
        f"{store} does not exist, so no arm has its own calibration: each decodes with "
        f"{without_own(fallback)}. Check [telemetry] calibrations (a relative path is from the directory the "
        f"agent starts in), or push a file there, which makes it (`{push_hint('ARM', store).command}`)"
    )


def without_own(fallback: str | None) -> str:
    """What an arm without its own calibration in the store decodes with, to follow "it decodes with":
    `fallback` is the agent's [telemetry] calibration ("": none set), None when it is not known (`twin
    calibration` runs without the agent's config). Not "the config's" when there is none: the arm then takes
    the nominal SO-101's and is flagged, which a person reading "the config's" would not look for."""
    nominal = "the nominal SO-101 calibration, and is flagged uncalibrated"
    if fallback is None:
        return f"the agent's [telemetry] calibration, or, where that is not set, {nominal}"
    if fallback:
        return f"the config's calibration ({fallback})"
    return f"{nominal} (the config sets no [telemetry] calibration)"


def push_hint(device: str, store: str) -> PushHint:
    """What to run so the agent whose store is `store` (store_location) picks up `device`'s calibration:
    `--store` for a directory, nothing more for the stack's bucket (the command's default), and for no store
    the setting to set first."""
    try:
        check_device(device)
    except ValueError as exc:
        text = f"no calibration can be kept: {exc}; give the arm's edge one that is (its deviceId)"
        return PushHint(store, "", text)
    push = f"twin calibration push {device} FILE"
    if not store:
        command = f"{push} --store DIR"
        return PushHint(
            store,
            command,
            f'this agent reads no per-arm calibrations: set {SETTING} = "DIR" in its config, restart it, '
            f"then run {command}",
        )
    if is_stack_store(store):
        return PushHint(
            store,
            push,
            f"push one: {push} (it writes to the deployed stack's CalibrationUri, {store}, which this agent "
            "reads)",
        )
    command = f"{push}{store_option(store)}"
    return PushHint(store, command, f"push one: {command} (this agent reads {store})")


def read_calibration(store: CalibrationStore, device: str) -> Calibration:
    """`device`'s calibration in `store`, checked as the agent checks it before an arm uses it (the watcher,
    and `twin calibration ls`, which marks a file the agent refuses). ValueError (not a valid SO-101
    calibration) or CalibrationStoreError (it could not be read): the reason the agent gives."""
    return parse_calibration(store.read(device), store.uri_of(device))


@dataclass(frozen=True)
class StoredCalibration:
    calibration: Calibration
    source: str  # where it was read from (s3://... or a path)
    version: str  # the store's version of the file it was read from


@dataclass(frozen=True)
class CalibrationChange:
    """What one poll changed for one arm: "picked up" (detail: the source), "refused" (detail: why) or
    "removed"."""

    device: str
    action: str
    detail: str = ""


@dataclass(frozen=True)
class CalibrationBook:
    """The calibrations in force, by device, why any file in the store was refused, and what the poll that
    made this book changed."""

    entries: Mapping[str, StoredCalibration] = field(default_factory=dict)
    problems: Mapping[str, str] = field(default_factory=dict)
    changes: tuple[CalibrationChange, ...] = ()
    # The arms in `problems` the store keeps a valid calibration for (KEPT_SUFFIX): only for them does a held
    # arm's refusal offer `twin calibration restore`, which for any other exits 1.
    restorable: frozenset[str] = frozenset()

    def calibrations(self) -> dict[str, Calibration]:
        return {device: e.calibration for device, e in self.entries.items()}

    def sources(self) -> dict[str, str]:
        return {device: e.source for device, e in self.entries.items()}

    def __iter__(self) -> Iterator[str]:
        return iter(self.entries)


class CalibrationWatcher:
    """Polls a store and calls `on_change(book)` whenever what is in force changes (module doc).

    `poll()` does one round on the calling thread (the agent's first, before it subscribes); `start()` runs
    them every `interval_s` on a thread of its own. A store that cannot be listed keeps the book as it is and
    is tried again next round.
    """

    def __init__(
        self,
        store: CalibrationStore,
        *,
        interval_s: float = DEFAULT_POLL_S,
        on_change: Callable[[CalibrationBook], None] = lambda _book: None,
        fallback: str = "",
        units: Units = Units.AUTO,
    ) -> None:
        self.store = store
        # The agent's [telemetry] calibration ("": none), what an arm whose file is removed decodes with.
        self.fallback = fallback
        self.units = units  # the agent's [telemetry] units: degrees use no calibration (refused_effect)
        self.interval_s = interval_s
        self._on_change = on_change
        self._book = CalibrationBook()
        # The version each device's file had when it was last read (good or refused), so it is read once;
        # and of each refused arm's kept file, with whether it is one restore takes.
        self._seen: dict[str, str] = {}
        self._kept_seen: dict[str, tuple[str, bool]] = {}
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.polls = 0
        self.failures = 0
        self.last_error = ""
        # The ignored names already warned about: once each, not every poll.
        self._ignored: set[str] = set()
        self._missing = False  # the store's directory was missing at the last poll (warned about once)

    @property
    def book(self) -> CalibrationBook:
        return self._book

    def poll(self) -> bool:
        """One round; True when the book changed (and `on_change` was called)."""
        self.polls += 1
        try:
            found = self.store.scan()
        except CalibrationStoreError as exc:
            self.failures += 1
            self.last_error = str(exc)
            log.warning("calibrations not refreshed: %s", exc, extra={"event": "calibration_store"})
            return False
        self.last_error = ""
        self._warn_missing(found.missing)
        self._warn_ignored(found.ignored)
        listing = found.calibrations
        entries = dict(self._book.entries)
        problems = {d: p for d, p in self._book.problems.items() if d in listing}
        changes = self._drop_removed(entries, listing)
        for device, version in sorted(listing.items()):
            if self._seen.get(device) == version:
                continue
            self._seen[device] = version
            source = self.store.uri_of(device)
            try:
                calibration = read_calibration(self.store, device)
            except (ValueError, CalibrationStoreError) as exc:
                if isinstance(exc, CalibrationStoreError):
                    # Not the file's fault (throttled, a network blip): read it again at the next poll,
                    # said once while it fails the same way. Marked seen, an arm held at the start stayed
                    # held until its file changed.
                    del self._seen[device]
                    if problems.get(device) == str(exc):
                        continue
                problems[device] = str(exc)
                changes.append(CalibrationChange(device, "refused", str(exc)))
                restorable = self._restorable(device, found.kept)
                self._log_refused(device, exc, kept=device in entries, restorable=restorable)
                continue
            problems.pop(device, None)
            entries[device] = StoredCalibration(calibration, source, version)
            changes.append(CalibrationChange(device, "picked up", source))
            log.info(
                "calibration of %s picked up from %s",
                device,
                source,
                extra={"event": "calibration", "device": device},
            )
        restorables = frozenset(d for d in problems if self._restorable(d, found.kept))
        self._kept_seen = {d: seen for d, seen in self._kept_seen.items() if d in problems}
        if not changes and problems == self._book.problems and restorables == self._book.restorable:
            return False
        self._book = CalibrationBook(entries, problems, tuple(changes), restorables)
        self._on_change(self._book)
        return True

    def _drop_removed(
        self, entries: dict[str, StoredCalibration], listing: Mapping[str, str]
    ) -> list[CalibrationChange]:
        """Take the arms whose file left the store out of `entries`; their changes, each logged."""
        changes = []
        for device in [d for d in entries if d not in listing]:
            del entries[device]
            self._seen.pop(device, None)
            changes.append(CalibrationChange(device, "removed"))
            # With the event's fields, as a pick-up's and a refusal's: a search of the log by device found
            # when an arm got its calibration but not when it lost it.
            log.info(
                "calibration of %s removed from the store: it decodes with %s",
                device,
                without_own(self.fallback),
                extra={"event": "calibration_removed", "device": device},
            )
        return changes

    def _restorable(self, device: str, kept: Mapping[str, str]) -> bool:
        """Whether a restore could put `device`'s kept calibration back: one is kept and it is valid (restore
        refuses one that is not, so offering it only led to an exit 1). Read for refused arms only, once a
        version of the kept file, as the arms' own files are."""
        version = kept.get(device)
        if version is None:
            return False
        seen = self._kept_seen.get(device)
        if seen is not None and seen[0] == version:
            return seen[1]
        try:
            data = self.store.read_kept(device)
            if data is not None:
                parse_calibration(data, f"{device}'s kept calibration")
            valid = data is not None
        except ValueError:
            valid = False
        except CalibrationStoreError:
            return False  # not read, not judged: asked again at the next poll
        self._kept_seen[device] = (version, valid)
        return valid

    def _log_refused(self, device: str, exc: Exception, *, kept: bool, restorable: bool) -> None:
        # `restore` only when a calibration is kept for the arm: with none it exits 1, a dead end.
        restore = f"twin calibration restore {device}{store_option(self.store.uri)}"
        log.warning(
            "calibration of %s refused, %s: %s; push a good file: %s%s",
            device,
            refused_effect(kept=kept, units=self.units),
            exc,
            push_hint(device, self.store.uri).command,
            f", or put back the one kept: {restore}" if restorable else "",
            extra={"event": "calibration_refused", "device": device},
        )

    def _warn_missing(self, missing: bool) -> None:
        # A mistyped path and a directory no push has made yet look alike: both hold nothing, and every arm
        # decodes with the config's calibration without a word, so the person is told, once.
        if missing and not self._missing:
            log.warning(
                "calibrations: %s",
                missing_store_notice(self.store.uri, self.fallback),
                extra={"event": "calibration_store_missing", "store": self.store.uri},
            )
        elif self._missing and not missing:
            log.info("calibrations: %s exists now; its files are read", self.store.uri)
        self._missing = missing

    def _warn_ignored(self, ignored: Sequence[str]) -> None:
        # The command that reaches this store (`--store DIR` for a directory): plain push is the stack's.
        push = push_hint("ARM", self.store.uri).command
        for name in sorted(set(ignored) - self._ignored):
            log.warning(
                "%s in %s is ignored: no arm reads it: %s",
                name,
                self.store.uri,
                ignored_fix(name, push),
                extra={"event": "calibration_ignored", "file": name},
            )
        self._ignored = set(ignored)

    def start(self) -> None:
        if self._thread is not None:
            return
        self._thread = threading.Thread(target=self._run, name="twin-calibrations", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.wait(self.interval_s):
            try:
                self.poll()
            except Exception:
                log.exception("calibration poll failed")

    def stop(self, timeout: float = 5.0) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout)
