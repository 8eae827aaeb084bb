#!/usr/bin/env python3
"""Checks README.md and the manual (docs/) offline; run by .ci/run, exits non-zero on any finding.

- Every relative link resolves: the file exists, and a `#anchor` names a heading of the target page
  (ids as mdBook and GitHub make them). Links from docs/ stay inside docs/, so the book has them too.
- Every page of docs/ is in docs/SUMMARY.md, so the book holds the whole manual.
- No process talk: the product's documents describe the software, not how it was built (no issue
  numbers, "this round", notes of a session, or paths of the machine a number was measured on).

    python3 scripts/check_docs.py
"""

from __future__ import annotations

import re
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
DOCS = ROOT / "docs"
LINK = re.compile(r"(?<!\!)\[(?:[^\]\[]|\[[^\]]*\])*\]\(([^)\s]+)(?:\s+\"[^\"]*\")?\)")
HEADING = re.compile(r"^(#{1,6})\s+(.*?)\s*#*\s*$")
PROCESS_TALK = [
    (re.compile(r"\b(this|previous|last|next) (round|stop)\b|\b(previous|last) session\b", re.I),
     "a working session's history"),
    (re.compile(r"\bsession notes\b", re.I), "notes outside the repository"),
    (re.compile(r"\bissue #?\d+\b|(?<![\w/&])#\d+\b", re.I), "an issue number"),
    (re.compile(r"/work/|notes/bench|\bbench\d+-[\w.-]*\.log\b"), "a path of the measuring machine"),
    (re.compile(r"\brounds?\b(?![\s-]+trips?)", re.I), "\"round\": say what was measured, not when"),
]
EXEMPT_FROM_PROCESS_CHECK: set[Path] = set()


def documents() -> list[Path]:
    return [ROOT / "README.md"] + sorted(p for p in DOCS.rglob("*.md") if "book" not in p.parts)


def prose_lines(text: str):
    """(line number, line) outside fenced code blocks, with inline code spans blanked."""
    fenced = False
    for number, line in enumerate(text.splitlines(), 1):
        if line.lstrip().startswith("```"):
            fenced = not fenced
            continue
        if not fenced:
            yield number, re.sub(r"`[^`]*`", "``", line)


def slug(heading: str) -> str:
    text = re.sub(r"\[([^\]]*)\]\([^)]*\)", r"\1", heading)  # a link's text
    text = re.sub(r"[`*]", "", text)
    out = []
    for ch in text.strip():
        if ch.isalnum() or ch in "_-":
            out.append(ch.lower())
        elif ch.isspace():
            out.append("-")
    return "".join(out)


def anchors(path: Path) -> set[str]:
    seen: dict[str, int] = {}
    out = set()
    fenced = False
    for line in path.read_text().splitlines():
        if line.lstrip().startswith("```"):
            fenced = not fenced
            continue
        m = None if fenced else HEADING.match(line)
        if m:
            base = slug(m.group(2))
            n = seen.get(base, 0)
            seen[base] = n + 1
            out.add(base if n == 0 else f"{base}-{n}")
    return out


def check_links(path: Path) -> list[str]:
    problems = []
    for number, line in prose_lines(path.read_text()):
        for target in LINK.findall(line):
            if re.match(r"^[a-z]+:", target):  # http:, https:, mailto:
                continue
            file_part, _, anchor = target.partition("#")
            dest = (path.parent / file_part).resolve() if file_part else path
            where = f"{path.relative_to(ROOT)}:{number}: link {target}"
            if not dest.exists():
                problems.append(f"{where}: {file_part} does not exist")
                continue
            if path.is_relative_to(DOCS) and not dest.is_relative_to(DOCS):
                problems.append(f"{where}: leaves docs/ (the book would not have it; name the file in code instead)")
            if anchor:
                if dest.suffix != ".md":
                    problems.append(f"{where}: an anchor into a file that is not a page")
                elif anchor not in anchors(dest):
                    problems.append(f"{where}: no heading #{anchor} in {dest.relative_to(ROOT)}")
    return problems


def check_summary() -> list[str]:
    summary = DOCS / "SUMMARY.md"
    if not summary.exists():
        return ["docs/SUMMARY.md is missing"]
    listed = {(DOCS / t.partition("#")[0]).resolve() for t in LINK.findall(summary.read_text())}
    return [f"{p.relative_to(ROOT)} is not in docs/SUMMARY.md" for p in documents()[1:]
            if p != summary and p.resolve() not in listed]


def check_process_talk(path: Path) -> list[str]:
    if path in EXEMPT_FROM_PROCESS_CHECK:
        return []
    problems = []
    text = path.read_text()
    prose = dict(prose_lines(text))
    for number, line in enumerate(text.splitlines(), 1):
        for pattern, why in PROCESS_TALK:
            # Paths count in code too; words only in prose (PromQL's round() is no process talk).
            m = pattern.search(line if why.startswith("a path") else prose.get(number, ""))
            if m:
                problems.append(f"{path.relative_to(ROOT)}:{number}: {why}: {m.group(0)!r}")
    return problems


def main() -> None:
    problems = check_summary()
    for path in documents():
        problems += check_links(path)
        problems += check_process_talk(path)
    for problem in problems:
        print(problem, file=sys.stderr)
    if problems:
        sys.exit(f"{len(problems)} problem(s) in README.md and docs/")
    print(f"README.md and docs/: {len(documents())} documents, links and anchors resolve, no process talk")


if __name__ == "__main__":
    main()
