"""Every relative link in the project's Markdown files leads to a file that exists, and every
`#anchor` to a heading of that file (GitHub's slugs)."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent
LINK = re.compile(r"\[[^\]]*\]\(([^)\s]+)\)")
FENCE = re.compile(r"^(```|~~~)")


def markdown_files() -> list[Path]:
    def kept(path: Path) -> bool:  # not in hidden folders (.venv, .git, caches) or run output
        parts = path.relative_to(REPO).parts
        return not any(p.startswith(".") or p in ("node_modules", "bench-results", "runs") for p in parts)

    return sorted(p for p in REPO.rglob("*.md") if kept(p))


def prose(path: Path) -> list[str]:
    """The file's lines outside fenced code blocks."""
    lines, fenced = [], False
    for line in path.read_text(encoding="utf-8").splitlines():
        if FENCE.match(line.lstrip()):
            fenced = not fenced
        elif not fenced:
            lines.append(line)
    return lines


def slug(heading: str) -> str:
    """GitHub's anchor for a heading: lower case, punctuation other than - and _ dropped,
    spaces as hyphens."""
    return re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-")


def anchors(path: Path) -> set[str]:
    out: set[str] = set()
    for line in prose(path):
        if m := re.match(r"^#{1,6}\s+(.*)$", line):
            base = slug(m.group(1))
            anchor, n = base, 1
            while anchor in out:  # a repeated heading gets -1, -2, ...
                anchor, n = f"{base}-{n}", n + 1
            out.add(anchor)
    return out


def test_slugs_follow_githubs_rule():
    assert slug("Where `nasa up` spends its time on 2 cores (`bench.up_profile`)") == (
        "where-nasa-up-spends-its-time-on-2-cores-benchup_profile")
    assert slug("bfloat16 pixel networks (`--pixel-precision bf16`)") == (
        "bfloat16-pixel-networks---pixel-precision-bf16")


@pytest.mark.parametrize("path", markdown_files(), ids=lambda p: str(p.relative_to(REPO)))
def test_relative_links_resolve(path: Path):
    broken = []
    for line in prose(path):
        for target in LINK.findall(re.sub(r"`[^`]*`", "", line)):
            if re.match(r"^[a-z]+:", target):  # http:, https:, mailto:
                continue
            file, _, anchor = target.partition("#")
            dest = (path.parent / file).resolve() if file else path
            if not dest.exists():
                broken.append(f"{target}: no {dest.relative_to(REPO) if dest.is_relative_to(REPO) else dest}")
            elif anchor and dest.suffix == ".md" and anchor not in anchors(dest):
                broken.append(f"{target}: no heading #{anchor} in {dest.relative_to(REPO)}")
    assert not broken, "\n".join(broken)
