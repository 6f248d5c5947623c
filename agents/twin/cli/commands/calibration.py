"""`twin calibration push|ls|rm|restore`: each arm's LeRobot calibration, in the store the agent watches.

LeRobot writes one calibration file per arm when it is calibrated (`lerobot-calibrate`), under
~/.cache/huggingface/lerobot/calibration/robots/so_follower/<id>.json. `push ARM FILE` checks the file is a
complete SO-101 calibration and stores it as ARM's; the agent picks it up within `calibration_poll_s` (30 s
by default), without a redeploy or a restart (docs/agent.md, "Calibration").

The store is the deployed stack's (its CalibrationUri output: s3://<bucket>/calibration), or the one --store
names: s3://bucket/prefix, or a directory for an agent on this machine ([telemetry] calibrations).

A push over another calibration, and `rm`, keep the one they replace beside it (`<ARM>.json.previous`, one
per arm; the stack's bucket keeps no versions), and `restore ARM` swaps it back in. A file named for another
arm that has a calibration of its own in the store, the very calibration another arm has there, or one for an
arm the stack's devices do not list (the host mirrors those only), is stored as asked, with a warning.

Exit codes:
  0  done
  1  the store could not be read or written (the message says why), `rm` found nothing to remove, or
     `restore` found nothing kept
  2  bad command line, or FILE is not an SO-101 calibration, or ARM is not a device id (1 to 64 letters,
     digits, '-', '_' or '.': the ids the stack mirrors, for every store)
  3  no AWS credentials or region; 4 stack not found; 5 the stack has no CalibrationUri output
"""

from __future__ import annotations

import argparse
import difflib
import shlex
import tempfile
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import TYPE_CHECKING

from twin.cli.output import Console

if TYPE_CHECKING:
    from collections.abc import Callable

    from twin.service.calibrations import CalibrationStore

    # What `_store` finds: the store, and the arms its stack mirrors (None: a --store, the whole fleet, or a
    # stack whose settings cannot be read), which only the stack's store knows.
    Found = tuple[CalibrationStore, tuple[str, ...] | None]

console = Console("calibration")

EXIT_OK = 0
EXIT_STORE = 1
EXIT_USAGE = 2
EXIT_SETUP = 3
EXIT_NO_STACK = 4
EXIT_NO_OUTPUTS = 5

# How many arms' files `ls` reads at once to check them as the agent does (a GET each on S3).
LS_READERS = 16

EPILOG = """examples:
  twin calibration push arm-003 ~/.cache/huggingface/lerobot/calibration/robots/so_follower/arm-003.json
  twin calibration ls
  twin calibration push arm-001 robots/so101/calibration/so101_follower_example.json --store out/calibration
exit codes: 0 done; 1 store error (or rm, restore: nothing there); 2 bad file or command line, ARM is not
  1..64 letters, digits, '-', '_' or '.', or the store holds an id differing from ARM only in case; 3 no AWS
  credentials or region; 4 stack not found; 5 the stack has no CalibrationUri output
store: --store, else the CalibrationUri output of --stack (default $SO101_TWIN_STACK, else stackName in
the checkout's twin.settings.toml, else So101TwinStack)
kept: a push over an arm's calibration, and rm, keep the one they replace (<ARM>.json.previous; ls shows
  it); `twin calibration restore ARM` puts it back, and again swaps back (a restore of what rm removed
  keeps nothing to swap back: rm again undoes it); `twin calibration rm --kept ARM` removes only the kept
  one, once it is no longer wanted"""


def register(subparsers: argparse._SubParsersAction) -> None:
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument(
        "--store",
        metavar="URI",
        help="s3://bucket/prefix or a directory (default: the deployed stack's CalibrationUri output)",
    )
    common.add_argument("--stack", default=None, help="stack whose store to use (default: as twin instance)")
    common.add_argument(
        "--region", default=None, help="AWS region (default: AWS_REGION, else the AWS config)"
    )
    parser = subparsers.add_parser(
        "calibration",
        help="store each arm's LeRobot calibration where the agent picks it up",
        description=__doc__.split("\n\n")[0],
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    actions = parser.add_subparsers(dest="action", metavar="ACTION", required=True)
    push = actions.add_parser(
        "push",
        parents=[common],
        help="check FILE is an SO-101 calibration and store it as ARM's",
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    push.add_argument("arm", metavar="ARM", help="the arm's device id, as its edge publishes it (arm-003)")
    push.add_argument("file", metavar="FILE", type=Path, help="the arm's LeRobot calibration JSON")
    ls = actions.add_parser(
        "ls",
        parents=[common],
        help="list the arms that have a calibration in the store (refused and not mirrored ones marked)",
    )
    rm = actions.add_parser(
        "rm",
        parents=[common],
        help="remove ARM's calibration (it decodes with the agent's [telemetry] calibration, else nominal)",
    )
    rm.add_argument("arm", metavar="ARM")
    rm.add_argument(
        "--kept",
        action="store_true",
        help="remove only the calibration kept for restore (<ARM>.json.previous), not ARM's own",
    )
    restore = actions.add_parser(
        "restore",
        parents=[common],
        help="put back the calibration ARM's last push or rm replaced (run again to swap back)",
    )
    restore.add_argument("arm", metavar="ARM")
    for action in (push, ls, rm, restore):
        action.set_defaults(func=run)


def _store(args: argparse.Namespace) -> Found | int:
    """The store --store names, else the stack's; an exit code when there is none."""
    from twin.service.calibrations import open_store

    if args.store:
        try:
            return open_store(args.store, region=args.region or ""), None
        except ValueError as exc:
            console.err(f"--store {exc}")
            return EXIT_USAGE
    from twin.ops import instance as lib

    twin = lib.TwinInstance(args.stack, region=args.region)
    codes = {lib.AwsSetupError: EXIT_SETUP, lib.StackNotFoundError: EXIT_NO_STACK}
    try:
        outputs = twin.outputs()
    except lib.TwinInstanceError as exc:
        # Without AWS the likelier wish is the local agent's store, which only --store reaches.
        local = " (or, for an agent on this machine, --store DIR: its [telemetry] calibrations)"
        console.err(f"{exc}{local if isinstance(exc, lib.AwsSetupError) else ''}")
        return codes.get(type(exc), EXIT_NO_OUTPUTS if isinstance(exc, lib.StackOutputsError) else EXIT_STORE)
    if not outputs.calibration_uri:
        console.err(
            f"stack {twin.stack_name} has no CalibrationUri output: it was deployed by an older version; "
            "deploy it once with this version (`cdk deploy`), or pass --store"
        )
        return EXIT_NO_OUTPUTS
    return open_store(outputs.calibration_uri, region=twin.region), _mirrored(outputs.settings)


def _mirrored(settings: str | None) -> tuple[str, ...] | None:
    """The device ids the stack's Settings output lists; None for the whole fleet or an unreadable output
    (an older stack), where nothing tells an arm the host does not mirror."""
    from twin.core.topics import ALL_DEVICES
    from twin.ops.deployed_settings import DeployedSettingsError, parse_deployed_settings

    try:
        devices = parse_deployed_settings(settings, "").values.get("devices")
    except DeployedSettingsError:
        return None
    if not isinstance(devices, list) or ALL_DEVICES in devices:
        return None
    return tuple(str(device) for device in devices)


def _store_flags(args: argparse.Namespace) -> str:
    """The flags that chose the store, for each command this one tells the user to run next: without them
    that command would reach another store (the stack's, not the directory this one wrote to)."""
    chosen = (("--store", args.store), ("--stack", args.stack), ("--region", args.region))
    return "".join(f" {flag} {shlex.quote(value)}" for flag, value in chosen if value)


def _arm_is_a_device_id(args: argparse.Namespace) -> bool:
    """False, having said why and what to do, when ARM breaks the device id rule a store keeps."""
    from twin.core.topics import policy_device_id_problem
    from twin.service.calibrations import check_device

    try:
        check_device(args.arm)
    except ValueError as exc:
        done = {"push": "stored", "rm": "removed"}.get(args.action, "changed")
        file = str(getattr(args, "file", ""))
        # `.JSON` too: the rule refuses an id ending in either case, and a Windows file may be named so.
        if args.arm.lower().endswith(".json") and file and policy_device_id_problem(file) is None:
            # The two arguments the other way round: the file first, then the arm.
            # With the flags that chose the store: without them the command reaches the stack's store.
            swapped = f"twin calibration push {shlex.quote(file)} {shlex.quote(args.arm)}{_store_flags(args)}"
            console.err(
                f"ARM {args.arm!r} is a file and FILE {file!r} a device id: the arm comes first "
                f"(`{swapped}`). Nothing was {done}"
            )
            return False
        console.err(
            f"ARM {exc}; use the device id the arm's edge publishes as, and give an edge whose id breaks "
            f"this rule a new one (its deviceId: docs/getting-started.md, part 3). Nothing was {done}"
        )
        return False
    return True


def run(args: argparse.Namespace) -> int:
    from twin.service.calibrations import CalibrationStoreError, StoreCredentialsError

    if args.action in ("push", "rm", "restore") and not _arm_is_a_device_id(args):
        return EXIT_USAGE
    data = b""
    if args.action == "push":
        read = _calibration_file(args.file)
        if isinstance(read, int):
            return read
        data = read
    found = _store(args)
    if isinstance(found, int):
        return found
    store, mirrored = found
    again = _store_flags(args)
    try:
        if args.action == "push":
            return _push(store, args.arm, args.file, data, again, mirrored=mirrored)
        if args.action == "rm":
            return _rm_kept(store, args.arm, again) if args.kept else _rm(store, args.arm, again)
        if args.action == "restore":
            return _restore(store, args.arm, again)
        return _ls(store, again, mirrored)
    except CalibrationStoreError as exc:
        console.err(str(exc))
        # No credentials is the setup problem exit 3 stands for, as without --store (the stack's lookup).
        return EXIT_SETUP if isinstance(exc, StoreCredentialsError) else EXIT_STORE


def _ls(store: CalibrationStore, again: str, mirrored: tuple[str, ...] | None = None) -> int:
    """A line per arm: its calibration's place, `refused: <why>` when the agent refuses that file, `not
    mirrored` for an arm the stack's `mirrored` devices do not list, and the kept one's place when there is
    one (an arm whose own was removed shows `(removed)`), marked when `restore` would refuse it, so what
    `restore` would bring back is seen before it is needed. Files no arm reads (named for no device id) are
    named on stderr."""
    from twin.service.calibrations import KEPT_SUFFIX, SUFFIX, ignored_fix

    found = store.scan()
    listing, kept = found.calibrations, found.kept
    if found.missing:
        # A mistyped --store read as an empty store: the user looked for their arms' files elsewhere.
        console.out(
            f"no calibration in {store.uri}: that directory does not exist; check --store against the "
            "agent's [telemetry] calibrations (a push makes it)"
        )
    elif not listing and not kept:
        console.out(f"no calibration in {store.uri}")
    refusals = _refusals(store, sorted(listing), _refusal)
    kept_refusals = _refusals(store, sorted(kept), _kept_refusal)
    for device in sorted(listing.keys() | kept):
        place = store.uri_of(device)
        line = f"{device}\t{place if device in listing else '(removed)'}"
        why = refusals.get(device, "")
        if why:
            line += f"\trefused: {why}"
        if mirrored is not None and device in listing and device not in mirrored:
            line += "\tnot mirrored"
        if device in kept:
            line += f"\tkept: {place.removesuffix(SUFFIX)}{KEPT_SUFFIX}"
            if kept_refusals.get(device):
                line += f" (refused, no restore: {kept_refusals[device]})"
        console.out(line)
    if any(refusals.values()):
        console.err(
            "refused: the agent does not use that file: an arm keeps the calibration it had until the agent "
            "starts again, and one with none (after a start) is held, its messages refused; push a good "
            f"file (`twin calibration push ARM FILE{again}`) or remove it"
        )
    unmirrored = [d for d in sorted(listing) if mirrored is not None and d not in mirrored]
    if unmirrored:
        console.err(
            f"not mirrored: the stack's devices ({_devices_named(mirrored or ())}) do not list "
            f"{_and(unmirrored)}, so no twin uses that calibration: add the arm to devices in "
            f"twin.settings.toml and deploy, or remove a mistyped one (`twin calibration rm ARM{again}`)"
        )
    if kept:
        console.err(
            f"kept: what a push or rm replaced; `twin calibration restore ARM{again}` swaps it back in when "
            f"it is a valid calibration, `twin calibration rm --kept ARM{again}` removes it"
        )
    push = f"twin calibration push ARM FILE{again}"
    for name in found.ignored:
        console.err(f"ignored: {name} (no arm reads it: {ignored_fix(name, push)})")
    return EXIT_OK


def _refusals(
    store: CalibrationStore, devices: list[str], refusal: Callable[[CalibrationStore, str], str]
) -> dict[str, str]:
    """`refusal` of each device (`_refusal`, `_kept_refusal`), LS_READERS at a time: on S3 each is a GET, and
    read one after another a large fleet's `ls` waits on a round trip per arm. The store's client exists by
    now (its scan made it)."""
    with ThreadPoolExecutor(max_workers=LS_READERS) as pool:
        return dict(zip(devices, pool.map(lambda device: refusal(store, device), devices), strict=True))


def _kept_refusal(store: CalibrationStore, device: str) -> str:
    """Why `restore` would refuse `device`'s kept calibration, in its words ("" when it would take it). A
    read that fails (no access, throttled) is the store's error, which stops `ls`: marked as refused, a
    kept file that may be good would read as one restore cannot bring back."""
    from twin.robot.calibration import parse_calibration

    kept = store.read_kept(device)
    try:
        if kept is not None:
            parse_calibration(kept, f"{device}'s kept calibration")
    except ValueError as exc:
        return str(exc)
    return ""


def _refusal(store: CalibrationStore, device: str) -> str:
    """Why the agent refuses `device`'s file in the store, in its words ("" when it takes it): the agent's
    own check, so `ls` shows what holds an arm rather than list a broken file like any other. A read that
    fails is the store's error, which stops `ls`, as for a kept file (`_kept_refusal`)."""
    from twin.service.calibrations import read_calibration

    try:
        read_calibration(store, device)
    except ValueError as exc:
        return str(exc)
    return ""


def _calibration_file(file: Path) -> bytes | int:
    """FILE's bytes once it parsed as a complete follower arm's SO-101 calibration; else an exit code, having
    said why."""
    from twin.robot.calibration import is_example, leader_problem, parse_calibration

    problem = leader_problem(file)
    if problem:
        console.err(f"{file} {problem}; push that one")
        return EXIT_USAGE
    try:
        data = file.expanduser().read_bytes()
        calibration = parse_calibration(data, str(file))
    except OSError as exc:
        console.err(f"cannot read {file}: {exc}")
        return EXIT_USAGE
    except ValueError as exc:
        console.err(str(exc))
        return EXIT_USAGE
    # Stored as LeRobot wrote it, once it parsed as a complete SO-101 calibration.
    console.out(f"{file}: an SO-101 calibration of motors {', '.join(calibration)}")
    if is_example(calibration):
        # Right for the edge simulator, which the guides pair it with; a real arm's twin would be off.
        console.err(
            f"note: {file} holds the example calibration that comes with the model, measured on no arm: "
            "fine with the edge simulator, but a real arm's twin would be off by the difference between "
            "its ranges and the example's; for a real arm push its own file (lerobot-calibrate writes "
            "it: robots/so101/calibration/README.md)"
        )
    return data


def _current(store: CalibrationStore, arm: str) -> tuple[bytes | None, dict[str, str]]:
    """ARM's calibration in the store (None: it has none), and the store's listing."""
    listing = store.listing()
    return (store.read(arm) if arm in listing else None), listing


def _case_twin_refused(
    store: CalibrationStore, arm: str, listing: dict[str, str], again: str, done: str
) -> bool:
    """True, having said why and what to do, when the store holds a calibration for an id that differs from
    ARM only in case: a write for ARM would be a second arm's file beside it."""
    from twin.core.topics import case_twin

    twin = case_twin(arm, listing)
    if twin is None:
        return False
    # Two arms to MQTT and S3, one file to a case-insensitive file system (a Mac's or Windows's directory
    # store), and most often one arm typed two ways.
    console.err(
        f"{store.uri} holds a calibration for {twin}, which differs from {arm} only in case: device ids "
        f"are case-sensitive, and a directory on a case-insensitive file system keeps both in one file. "
        f"Use {twin} if that is this arm (the id its edge publishes as), or remove {twin}'s first "
        f"(`twin calibration rm {twin}{again}`). Nothing was {done}"
    )
    return True


def _push(
    store: CalibrationStore,
    arm: str,
    file: Path,
    data: bytes,
    again: str,
    *,
    mirrored: tuple[str, ...] | None,
) -> int:
    current, listing = _current(store, arm)
    if _case_twin_refused(store, arm, listing, again, "stored"):
        return EXIT_USAGE
    if current == data:
        console.out(f"{arm}: {store.uri_of(arm)} already holds this calibration; nothing written")
        if mirrored is not None and arm not in mirrored:
            # A re-push is often a retry of a twin that never moved: the reason is the same as the first
            # push's, whose warning may have scrolled away. Removing it is an rm, as if just stored.
            _warn_unmirrored(arm, mirrored, f"It was stored before ({_undo(store, arm, None, again)})")
        return EXIT_OK
    if mirrored is not None and arm not in mirrored:
        # Stored all the same: an arm may be calibrated before it is deployed.
        _warn_unmirrored(arm, mirrored, f"It is stored as asked ({_undo(store, arm, current, again)})")
    named_for = file.stem
    if named_for != arm and named_for in listing:
        # LeRobot names the file for the arm it calibrated: this may be another arm's, pushed by mistake.
        console.err(
            f"warning: {file.name} is named for {named_for}, which has a calibration of its own in "
            f"{store.uri}; it is stored as {arm}'s, as asked ({_undo(store, arm, current, again)})"
        )
    same = _same_calibration(store, arm, data, listing)
    if same:
        # No two arms share a calibration (LeRobot measures each arm's ranges by hand): a copy is a slip, but
        # maybe an earlier push's (arm-002's file pushed as arm-003's, now as arm-002's own), so both are
        # named and neither is blamed.
        whose = "the other's" if len(same) == 1 else "another's"
        named = (
            f" {file.name} is named for {arm}, so {_and(same)}'s may be the copy." if named_for == arm else ""
        )
        console.err(
            f"warning: {file.name} is the calibration {_arms_have(same)} in {store.uri}; each arm has its "
            f"own, so one of {_and([arm, *same])} has {whose}, and its twin shows a wrong pose.{named} It is "
            f"stored as {arm}'s, as asked; find the arm it was not measured on and push that arm's own file "
            f"(lerobot-calibrate on its computer) ({_undo(store, arm, current, again)})"
        )
    # The one it replaces is kept first: if that fails, nothing has changed.
    why = "" if current is None else _invalid(store, arm, current)
    kept = None if current is None else _keep(store, arm, current, why)
    where = store.write(arm, data)
    console.out(f"{arm}: {where} (the agent picks it up within its calibration_poll_s, 30 s by default)")
    if current is not None:
        console.out(f"{arm}: {_kept_said(arm, why, kept, again)}")
    return EXIT_OK


def _warn_unmirrored(arm: str, mirrored: tuple[str, ...], stored: str) -> None:
    """Say that the stack does not mirror ARM, so no twin uses its calibration (`stored`: where that leaves
    the calibration, and its undo)."""
    # The host subscribes to the listed arms' topics only: a mistyped id would sit in the bucket unused,
    # told only in the host's log.
    console.err(
        f"warning: the stack mirrors {_devices_named(mirrored)} (its devices setting), not {arm}"
        f"{_nearest(arm, mirrored)}, so no twin uses this calibration yet; if {arm} is the id its edge "
        f"publishes as, add it to devices in twin.settings.toml and deploy (`npx cdk deploy`), else push "
        f"under the arm's id. {stored}"
    )


def _keep(store: CalibrationStore, arm: str, current: bytes, why: str) -> str | None:
    """Keep what a push or rm replaces, for a restore; where it is kept. Not a file that is no valid
    calibration (`why` it is not, "" when it is one) in place of a valid one kept from before (None): that
    one is what a restore can still put back, and a truncated upload is worth less than the arm's last good
    calibration."""
    if why:
        before = store.read_kept(arm)
        if before is not None and not _invalid(store, arm, before):
            return None
    return store.write_kept(arm, current)


def _kept_said(arm: str, why: str, kept: str | None, again: str) -> str:
    """What push and rm say of the file they replaced (`why` it was no valid calibration, "" when it was
    one; `kept`: where _keep put it, None: nowhere)."""
    restore = f"`twin calibration restore {arm}{again}`"
    if kept is None:
        return (
            f"the file it replaced was not a valid calibration ({why}) and is not kept, so the valid one "
            f"kept from before stays for {restore}"
        )
    if why:
        return (
            f"the file it replaced was not a valid calibration ({why}), so no restore can put it back; it is "
            f"kept at {kept} all the same"
        )
    return f"the one it replaced is kept at {kept} ({restore})"


def _invalid(store: CalibrationStore, arm: str, data: bytes) -> str:
    """Why `data`, ARM's file in the store, is no calibration the agent or `restore` takes ("" when it is
    one): push and rm keep it all the same, but must not offer a restore that would refuse it."""
    from twin.robot.calibration import parse_calibration

    try:
        parse_calibration(data, store.uri_of(arm))
    except ValueError as exc:
        return str(exc)
    return ""


def _arms_have(arms: list[str]) -> str:
    """The words for one or more arms having a thing: "arm-001 already has", "a and b already have"."""
    return f"{_and(arms)} already {'has' if len(arms) == 1 else 'have'}"


def _and(arms: list[str]) -> str:
    """ "a", "a and b", "a, b and c"."""
    return arms[0] if len(arms) == 1 else f"{', '.join(arms[:-1])} and {arms[-1]}"


def _same_calibration(store: CalibrationStore, arm: str, data: bytes, listing: dict[str, str]) -> list[str]:
    """The other arms whose calibration in the store is `data`, byte for byte. Only files of its size are
    read (every store's version ends in `:<size>`), so a push over a fleet's store reads few."""
    size = f":{len(data)}"
    return sorted(d for d, v in listing.items() if d != arm and v.endswith(size) and store.read(d) == data)


# A stack may list up to MAX_LISTED_DEVICES arms: a warning names the first few, not a screenful.
SHOWN_DEVICES = 8


def _devices_named(mirrored: tuple[str, ...]) -> str:
    rest = len(mirrored) - SHOWN_DEVICES
    shown = ", ".join(mirrored[:SHOWN_DEVICES])
    return f"{shown} and {rest} more" if rest > 0 else shown


# Ids shorter than this get no one-character-off hint (difflib's 0.8 never offered one either).
MIN_SLIP_LENGTH = 5
# Characters a person types for one another in an id: a letter O for a zero, an l or I for a one.
_LOOK_ALIKE = str.maketrans("oli", "011")


def _slips(arm: str, listed: str) -> int:
    """How many characters `listed` differs from `arm` in, over case and look-alike characters (3 for a
    different length: an inserted or dropped character is left to difflib)."""
    a, b = (x.casefold().translate(_LOOK_ALIKE) for x in (arm, listed))
    return sum(x != y for x, y in zip(a, b, strict=True)) if len(a) == len(b) else 3


def _nearest(arm: str, mirrored: tuple[str, ...]) -> str:
    """The listed ids `arm` is most likely a slip for, offered as what was meant: a case or look-alike slip
    first (arm-0O3 for arm-003), then one character off, then one inserted or dropped (difflib)."""
    by_slips = {d: _slips(arm, d) for d in mirrored}
    fewest = min(by_slips.values(), default=3)
    # One character off a short id (b1, a1) is as likely another id as a slip: case and look-alikes only.
    allowed = 1 if len(arm) >= MIN_SLIP_LENGTH else 0
    close = sorted(d for d, n in by_slips.items() if n == fewest) if fewest <= allowed else []
    if not close:
        # Not difflib.get_close_matches: its n best cut ties off unsaid (for arm-15 among arm-001..arm-150:
        # arm-150, arm-145 and arm-135 of 7 as close, arm-015 not among them) and fill up with less close
        # ids; here all ties count.
        ratios = {d: difflib.SequenceMatcher(None, arm, d).ratio() for d in mirrored}
        best = max(ratios.values(), default=0.0)
        close = sorted(d for d, ratio in ratios.items() if ratio == best) if best >= 0.8 else []
    if not close:
        return ""
    more = f", or {len(close) - 3} more as close" if len(close) > 3 else ""
    return f" (did you mean {' or '.join(close[:3])}{more}?)"


def _undo(store: CalibrationStore, arm: str, current: bytes | None, again: str) -> str:
    """How a push about to replace `current` (None: the arm has none) is undone, if it was a slip."""
    if current is not None and _invalid(store, arm, current):
        return "if that was a slip, push the right file: the one it replaces is not a valid calibration"
    if current is not None:
        return f"if that was a slip: `twin calibration restore {arm}{again}`"  # push keeps what it replaces
    if store.read_kept(arm) is None:
        return f"if that was a slip: `twin calibration rm {arm}{again}`"
    # rm keeps what it removes, in place of the calibration kept from before (an rm's): that one would go.
    return (
        f"if that was a slip, `twin calibration rm {arm}{again}` takes it out but keeps it in place of the "
        f"calibration kept from before, which `twin calibration ls{again}` shows: save that one first"
    )


def _rm(store: CalibrationStore, arm: str, again: str) -> int:
    from twin.service.calibrations import without_own

    current, _ = _current(store, arm)
    if current is None:
        console.err(f"{arm} has no calibration in {store.uri}")
        return EXIT_STORE
    why = _invalid(store, arm, current)
    kept = _keep(store, arm, current, why)
    store.delete(arm)
    # The agent's config is not known here: it may set no [telemetry] calibration.
    console.out(f"{arm}: removed from {store.uri}; it decodes with {without_own(None)}")
    console.out(f"{arm}: {_kept_said(arm, why, kept, again)}")
    return EXIT_OK


def _rm_kept(store: CalibrationStore, arm: str, again: str) -> int:
    """Remove the calibration kept for ARM's restore: what push and rm keep is otherwise never taken away,
    and `ls` lists a removed arm's for good."""
    from twin.service.calibrations import KEPT_SUFFIX, SUFFIX

    if store.read_kept(arm) is None:
        console.err(f"{arm} has no kept calibration in {store.uri} (`twin calibration ls{again}` lists them)")
        return EXIT_STORE
    store.delete_kept(arm)
    where = f"{store.uri_of(arm).removesuffix(SUFFIX)}{KEPT_SUFFIX}"
    current, _ = _current(store, arm)
    now = "its own calibration stays" if current is not None else "it has no calibration in the store now"
    console.out(f"{arm}: removed {where}; {now}, and `restore` has nothing to put back")
    return EXIT_OK


def _restore(store: CalibrationStore, arm: str, again: str) -> int:
    """The kept calibration becomes ARM's again, and the one it replaces is kept in its place: a second
    restore swaps back, unless what it replaced is no valid calibration (a restore would refuse it)."""
    from twin.robot.calibration import parse_calibration
    from twin.service.calibrations import KEPT_SUFFIX, CalibrationStoreError

    kept = store.read_kept(arm)
    if kept is None:
        # Also after rm then restore, which kept nothing (there was no calibration to keep): rm goes back.
        current, _ = _current(store, arm)
        back = f"; `twin calibration rm {arm}{again}` removes the one it has" if current is not None else ""
        console.err(
            f"{arm} has no kept calibration in {store.uri}: push and rm keep the one they replace, and a "
            f"restore of what rm removed keeps none{back}"
        )
        return EXIT_STORE
    try:
        parse_calibration(kept, f"{arm}'s kept calibration")
    except ValueError as exc:
        console.err(f"{exc}; nothing restored")
        return EXIT_STORE
    current, listing = _current(store, arm)
    # rm ARM-001, push arm-001, then restore ARM-001: the kept file has no twin, the one it goes back to has.
    if _case_twin_refused(store, arm, listing, again, "restored"):
        return EXIT_USAGE
    if current is None:
        where = store.write(arm, kept)
        store.delete_kept(arm)
        console.out(f"{arm}: {where} holds the calibration rm removed again")
        return EXIT_OK
    kept_at = store.write_kept(arm, current)
    try:
        where = store.write(arm, kept)
    except CalibrationStoreError:
        # The kept one's place now holds the current one: the kept one is only here. Saved where its
        # owner can push it again rather than lost.
        saved = _rescue(f"{arm}{KEPT_SUFFIX}", kept)
        console.err(
            f"{arm}'s kept calibration is saved in {saved}: `twin calibration push {arm} {saved}{again}`"
        )
        raise
    why = _invalid(store, arm, current)
    if why:
        # A second restore would refuse it: say so, as push and rm do, rather than offer the swap back.
        said = _kept_said(arm, why, kept_at, again)
        console.out(f"{arm}: {where} holds the kept calibration again; {said}")
        return EXIT_OK
    console.out(
        f"{arm}: {where} holds the kept calibration again; the one it replaced is kept in its place "
        "(restore again to swap back)"
    )
    return EXIT_OK


def _rescue(name: str, data: bytes) -> Path:
    """`data` written to a new file named `name` (`name.1`, `name.2` ... when a different one is there: an
    earlier rescue's copy is somebody's only one too) in the working directory, or in the temporary
    directory when that one cannot be written; its path."""
    from twin.service.persist import numbered

    for directory in (Path.cwd(), Path(tempfile.gettempdir())):
        for path in numbered(directory / name, 100):
            try:
                with path.open("xb") as fh:
                    fh.write(data)
                return path.absolute()
            except FileExistsError:
                if _holds(path, data):
                    return path.absolute()
            except OSError:
                break
    raise OSError(f"the kept calibration could not be written anywhere (tried {Path.cwd()} and the temp dir)")


def _holds(path: Path, data: bytes) -> bool:
    try:
        return path.read_bytes() == data
    except OSError:
        return False
