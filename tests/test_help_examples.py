"""Every example a `twin ... --help` shows is run, as written, and must succeed.

The examples are the lines under an "examples:" heading of any command's help. Each runs in bash in a
sandbox that holds what the examples name: this checkout's `examples/` and `robots/` in the working
directory, a LeRobot calibration where LeRobot keeps it under a fresh HOME, and, for the commands that reach
the deployed stack, AWS: moto's server stands in for CloudFormation and S3 (AWS cannot be reached from here;
the AWS SDK follows AWS_ENDPOINT_URL), holding a stack with the outputs the real one has."""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
from collections.abc import Iterator
from pathlib import Path

import boto3
import pytest
from moto_s3 import REGION, MotoS3
from twin.cli.main import build_parser

REPO = Path(__file__).resolve().parents[1]
EXAMPLE_CALIBRATION = REPO / "robots" / "so101" / "calibration" / "so101_follower_example.json"

pytestmark = pytest.mark.slow


def walk(parser: argparse.ArgumentParser, path: tuple[str, ...] = ("twin",)) -> Iterator[tuple[str, ...]]:
    yield path
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                yield from walk(sub, (*path, name))


def help_examples() -> list[str]:
    """The example lines of every command's help, each once (a parent's epilog repeats in its children's)."""
    parser = build_parser()
    found: dict[str, None] = {}
    for path in walk(parser):
        sub = parser
        for name in path[1:]:
            sub = next(a for a in sub._actions if isinstance(a, argparse._SubParsersAction)).choices[name]
        lines = sub.format_help().splitlines()
        for i, line in enumerate(lines):
            if line.strip() != "examples:":
                continue
            for example in lines[i + 1 :]:
                if not example.startswith("  twin "):
                    break
                found[example.strip()] = None
    return list(found)


def test_the_examples_are_found() -> None:
    examples = help_examples()
    # The commands whose help shows examples today; a new example joins the runs below by itself.
    assert {e.split()[1] for e in examples} >= {"calibration", "config", "render"}
    assert len(examples) >= 9


@pytest.fixture(scope="module")
def sandbox(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[Path, dict[str, str]]]:
    root = tmp_path_factory.mktemp("help-examples")
    work = root / "work"
    work.mkdir()
    for name in ("examples", "robots"):
        (work / name).symlink_to(REPO / name)
    home = root / "home"
    lerobot = home / ".cache/huggingface/lerobot/calibration/robots/so_follower"
    lerobot.mkdir(parents=True)
    for arm in ("arm-001", "arm-003"):
        shutil.copy(EXAMPLE_CALIBRATION, lerobot / f"{arm}.json")
    empty = root / "aws-config"
    empty.write_text("")
    aws = MotoS3(bucket="so101twinstack-history")
    try:
        boto3.client(
            "cloudformation",
            endpoint_url=aws.endpoint,
            region_name=REGION,
            aws_access_key_id="testing",
            aws_secret_access_key="testing",
        ).create_stack(
            StackName="So101TwinStack",
            TemplateBody=json.dumps(
                {
                    "Resources": {"Topic": {"Type": "AWS::SNS::Topic"}},
                    "Outputs": {
                        "InstanceId": {"Value": "i-0123456789abcdef0"},
                        "DcvUrl": {"Value": "https://192.0.2.1:8443/#console"},
                        "CalibrationUri": {"Value": "s3://so101twinstack-history/calibration"},
                    },
                }
            ),
        )
        env = {
            "PATH": f"{REPO / '.venv' / 'bin'}:{os.environ['PATH']}",
            "HOME": str(home),
            "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl"),
            "PYOPENGL_PLATFORM": os.environ.get("PYOPENGL_PLATFORM", "egl"),
            "AWS_ENDPOINT_URL": aws.endpoint,
            "AWS_ACCESS_KEY_ID": "testing",
            "AWS_SECRET_ACCESS_KEY": "testing",
            "AWS_REGION": REGION,
            "AWS_DEFAULT_REGION": REGION,
            "AWS_CONFIG_FILE": str(empty),
            "AWS_SHARED_CREDENTIALS_FILE": str(empty),
            "AWS_EC2_METADATA_DISABLED": "true",
        }
        yield work, env
    finally:
        aws.close()


@pytest.mark.parametrize("example", help_examples())
def test_every_help_example_runs(example: str, sandbox: tuple[Path, dict[str, str]]) -> None:
    work, env = sandbox
    result = subprocess.run(
        ["bash", "-c", f"set -euo pipefail; {example}"],
        cwd=work,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
    )
    assert result.returncode == 0, (
        f"{example}\nstdout: {result.stdout[-2000:]}\nstderr: {result.stderr[-2000:]}"
    )


def test_replay_takes_the_times_its_help_suggests(tmp_path: Path) -> None:
    """`--from` and `--to` as the help spells them (1h, 10m ago, now, --from=-1h) get past the command line:
    what fails next is the empty history, not argparse (exit 2)."""
    from twin.cli.main import main

    history = str(tmp_path / "none")
    for times in (["--from", "1h", "--to", "now"], ["--from=-1h", "--to", "10m"]):
        code = main(["replay", "--history", history, "--device", "arm-001", *times])
        assert code == 1, times
