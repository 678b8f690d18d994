"""Every flag the user's guide shows on a `nasa ...` or `python -m services.<role>` command line is
one that command's parser takes, so the guide cannot drift from the code. Nothing runs: tyro lists each
command's flags from its dataclass and the flags are looked up there."""

from __future__ import annotations

import ast
import contextlib
import io
import re
from functools import cache

import pytest
import tyro
from test_docs_links import FENCE, REPO

from nasa.auth import AuthInit, AuthTls
from nasa.cli import COMMANDS, TrainCommand
from nasa.plot import PlotCommand
from nasa.reproduce import ReproduceCommand
from nasa.up import StatusCommand, UpCommand
from services.actor.actor import ActorArgs
from services.evaluator.evaluator import EvaluatorArgs
from services.learner.health import LearnerArgs
from services.replay.service import ReplayArgs
from services.robot_bridge.main import BridgeArgs
from services.router.__main__ import RouterArgs

# A deprecated tyro call fails here, not in the tyro release that drops it.
pytestmark = pytest.mark.filterwarnings("error::DeprecationWarning")

# The guide: what a user reads to run the system.
GUIDE = ["README.md", "docs/architecture.md", "docs/deployment.md", "docs/reference.md",
         "services/README.md", "services/robot_bridge/README.md"]

# Each command line as the docs write it, and the dataclass its parser is made from.
PARSERS: dict[str, type] = {
    "nasa up": UpCommand, "nasa train": TrainCommand, "nasa reproduce": ReproduceCommand,
    "nasa plot": PlotCommand, "nasa status": StatusCommand, "nasa auth init": AuthInit,
    "nasa auth tls": AuthTls,
    "python -m services.actor": ActorArgs, "python -m services.evaluator": EvaluatorArgs,
    "python -m services.learner": LearnerArgs, "python -m services.replay": ReplayArgs,
    "python -m services.router": RouterArgs, "python -m services.robot_bridge": BridgeArgs,
}
# `nasa reproduce ... -- FLAGS`: the flags after `--` go to each `nasa train`.
AFTER_DASHES = {"nasa reproduce": "nasa train"}
# Where a command line ends inside a snippet: a comment, the next command, a redirection.
ENDS = {"&&", "||", ";", "|", ">", "2>&1"}
# Flags the guide names alone that belong to other tools: docker's, bench.multihost's, kubectl's.
OTHER_TOOLS = {"--cpus", "--delay-ms", "--from-file"}
SPAN = re.compile(r"`([^`]+)`")
FLAG = re.compile(r"--[A-Za-z][\w-]*")


@cache
def flags_of(command: str) -> frozenset[str]:
    """The flags `command`'s parser takes, as tyro's shell completion lists them for its dataclass
    (`--tyro-write-completion`, which tyro offers where its deprecated get_parser was used): the
    script carries them as one Python literal, COMPLETION_SPEC."""
    script = io.StringIO()
    with contextlib.redirect_stdout(script), pytest.raises(SystemExit):  # tyro exits once written
        tyro.cli(PARSERS[command], prog=command, args=["--tyro-write-completion", "bash", "-"])
    spec = next(line for line in script.getvalue().splitlines() if line.startswith("COMPLETION_SPEC = "))
    options = ast.literal_eval(spec.removeprefix("COMPLETION_SPEC = "))["options"]
    return frozenset(flag for option in options for flag in option["flags"])


def snippets(text: str) -> list[str]:
    """The code a Markdown text shows: each line of a fenced or indented block (a line ending in
    a backslash joined to the next) and each inline code span of a paragraph (a list item's
    indented lines included)."""
    out, fenced, paragraph, joined = [], False, [], ""
    for line in [*text.splitlines(), ""]:
        if FENCE.match(line.lstrip()):
            fenced = not fenced
            continue
        if fenced or (line.startswith("    ") and "`" not in line):  # not a list's indented text
            joined += " " + line.strip().removesuffix("\\")
            if not line.rstrip().endswith("\\"):
                out.append(joined)
                joined = ""
            continue
        if line.strip():
            paragraph.append(line)
        else:  # a code span may run over a line break, never over a paragraph
            out += SPAN.findall(" ".join(paragraph).replace("\\|", "|"))
            paragraph = []
    return out


def words_of(snippet: str) -> list[str]:
    """The snippet's words, with `.venv/bin/nasa` and `python -m nasa` written as `nasa`."""
    words = []
    for word in snippet.replace("\\|", "|").split():
        if word.endswith("/nasa"):
            word = "nasa"
        elif re.fullmatch(r"(.*/)?python3?", word):
            word = "python"
        if word in ("nasa", "nasa.cli") and words[-2:] == ["python", "-m"]:
            words[-2:] = []
            word = "nasa"
        words.append(word)
    return words


def command_lines(snippet: str) -> list[tuple[str, list[str]]]:
    """Each known command in a snippet with the words after it, up to where its line ends."""
    words, found = words_of(snippet), []
    for i in range(len(words)):
        for take in (3, 2):
            name = " ".join(words[i:i + take])
            if name in PARSERS:
                rest = words[i + take:]
                end = next((j for j, w in enumerate(rest) if w in ENDS or w.startswith("#")), len(rest))
                found.append((name, rest[:end]))
                break
    return found


def unknown_flags(text: str) -> list[str]:
    """`command: --flag` for each flag of a command line in `text` that the command does not take."""
    bad = []
    for snippet in snippets(text):
        for command, words in command_lines(snippet):
            parser = command
            for word in words:
                if word == "--" and command in AFTER_DASHES:
                    parser = AFTER_DASHES[command]
                    continue
                for part in word.split("|"):  # `--a|--b`, `[--steps N]`, `--x=VALUE`
                    flag = part.strip("[](),").split("=", 1)[0]
                    if FLAG.fullmatch(flag) and flag.replace("_", "-") not in flags_of(parser):
                        bad.append(f"{parser}: {flag} (in `{snippet.strip()}`)")
    return bad


def test_every_command_of_nasa_has_a_parser_here():
    """A command added to `nasa` gets its flags checked too (`auth` through its two subcommands)."""
    expected = {f"nasa {name}" for name in COMMANDS if name != "auth"} | {"nasa auth init", "nasa auth tls"}
    assert expected <= set(PARSERS)


def test_a_misspelled_flag_is_found_in_code_blocks_and_inline_spans():
    text = ("```bash\n.venv/bin/nasa up --actors 2 \\\n  --eval-evry 200   # and --not-a-flag\n```\n\n"
            "Run `nasa train --resume DIR [--step N]` or\n"
            "`nasa reproduce --seeds 2 -- --latent-dim 8 --seeds 3`.\n\n"
            "    python -m services.router --listen tcp/0.0.0.0:7447 --joins tls/a:7447\n")
    found = [line.split(" (in ")[0] for line in unknown_flags(text)]
    assert found == ["nasa up: --eval-evry", "nasa train: --step", "nasa train: --seeds",
                     "python -m services.router: --joins"]


def test_the_readme_shows_each_command_with_its_flags():
    """The check finds the README's command lines (it cannot pass by reading none)."""
    readme = snippets((REPO / "README.md").read_text(encoding="utf-8"))
    commands = {command for s in readme for command, words in command_lines(s) if words}
    assert {"nasa up", "nasa train", "nasa reproduce", "nasa plot", "nasa status", "nasa auth init",
            "nasa auth tls"} <= commands


@pytest.mark.parametrize("doc", GUIDE)
def test_every_flag_on_a_command_line_of_the_guide_exists(doc: str):
    bad = unknown_flags((REPO / doc).read_text(encoding="utf-8"))
    assert not bad, "\n".join(bad)


@pytest.mark.parametrize("doc", GUIDE)
def test_every_flag_named_alone_is_a_flag_of_some_command(doc: str):
    """A code span of flags with no command (`--flag`, `--flag VALUE --other`): each is a flag of
    one of the commands (a service's, say), so a flag renamed in the code cannot live on in the text."""
    known = OTHER_TOOLS.union(*(flags_of(command) for command in PARSERS))
    alone = {word.strip("[](),").split("=", 1)[0]
             for s in snippets((REPO / doc).read_text(encoding="utf-8")) if s.startswith("--")
             for word in s.split()}
    unknown = {flag for flag in alone if FLAG.fullmatch(flag)} - known
    assert not unknown, sorted(unknown)
