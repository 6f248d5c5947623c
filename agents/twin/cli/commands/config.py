"""`twin config example|reference|check`: the agent config's every key, and whether a file is valid.

`example` prints a config with every key at its default, each with what it means (examples/agent.toml is
this output); `reference` prints the same as a Markdown table (docs/configuration.md is this output); `check`
loads files exactly as `twin run --config` does and says whether the agent would start with them.

Exit codes: 0 done (check: valid); 2 bad command line, or the files are not a valid config (the reason names
the key and the fix).
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING

from twin.cli.output import Console

if TYPE_CHECKING:
    from twin.service.config import AgentConfig

console = Console("config")

EPILOG = """examples:
  twin config example > my-agent.toml
  twin config check examples/agent.toml
  twin config reference"""


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "config",
        help="print every agent config key (as a file or a table), or check a config file",
        description=__doc__.split("\n\n")[0],
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    actions = parser.add_subparsers(dest="action", metavar="ACTION", required=True)
    actions.add_parser("example", help="a config with every key at its default and what it means (TOML)")
    actions.add_parser("reference", help="every key, its type, default and meaning (Markdown)")
    check = actions.add_parser(
        "check", help="load FILE (several: each on top of the ones before) as `twin run --config` would"
    )
    check.add_argument("files", metavar="FILE", type=Path, nargs="+")
    parser.set_defaults(func=run)
    for action in actions.choices.values():
        action.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from twin.service.config import ConfigError, config_notes, connection_plan, health_plan, load_config
    from twin.service.config_reference import render_example, render_reference

    if args.action == "example":
        console.out(render_example().rstrip("\n"))
    elif args.action == "reference":
        console.out(render_reference().rstrip("\n"))
    else:
        try:
            config = load_config(args.files)
        except ConfigError as exc:
            console.err(str(exc))
            return 2
        console.out(f"{', '.join(str(f) for f in args.files)}: a valid agent config")
        # What a broker policy must allow (on the twin host, the stack's role; docs/scaling.md).
        console.out(connection_plan(config))
        console.out(health_plan(config))  # the rate the loss estimate and the stale line take as the edges'
        # Valid, so still exit 0: what the agent would start with, and what it would warn of.
        for note in config_notes(args.files, config) + _store_notes(config):
            console.out(f"note: {note}")
    return 0


def _store_notes(config: AgentConfig) -> list[str]:
    """A calibration store directory that is not there, as `twin run` started here would warn at its start: a
    mistyped path was called a valid config, and every arm then decoded with the config's calibration."""
    from twin.service.calibrations import DirectoryStore, missing_store_notice, open_store

    uri = config.telemetry.calibrations
    store = open_store(uri) if uri else None
    if not isinstance(store, DirectoryStore) or store.path.exists():
        return []  # none, on S3 (made by the stack), or there
    notice = missing_store_notice(store.uri, config.telemetry.calibration)
    return [f"[telemetry] calibrations = {uri!r}: {notice}"]
