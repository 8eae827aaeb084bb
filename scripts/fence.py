#!/usr/bin/env python3
"""The fence: keeps the crates' structure from regressing.

Fails (exit 1) on:
  - an import circle between the files of one crate (read from `use crate::`, `use super::` and
    `use self::` lines, a name re-exported by `pub use` followed to the file that defines it);
  - where a crate's lib.rs declares its layers (a `//! Layers, from the top down: a, b | c | d`
    line: `|` between floors, `,` within one), an import from a lower floor to a higher one;
  - a product source file over MAX_FILE_LINES lines before its test module;
  - a function over MAX_FN_LINES lines that .ci/fence-allow.txt does not list (each entry says why).

Prints its numbers either way. Test files (tests.rs, tests/ folders, the tests crate) are left out.
Usage: python3 scripts/fence.py [ROOT]
"""

import re
import sys
from pathlib import Path

MAX_FILE_LINES = 900
MAX_FN_LINES = 150
CRATES = ["core", "baselines", "proto", "client", "server", "lab", "examples"]
# The research tenant does not ship: its experiments are held to the import rules, not to the
# product's file and function sizes.
NOT_PRODUCT = {"lab"}
ALLOW = Path(".ci/fence-allow.txt")

TEST_MODULE = re.compile(r"^\s*#\[cfg\(test\)\]\s*$")
MOD_DECL = re.compile(r"^\s*(?:pub(?:\([^)]*\))?\s+)?mod\s+(\w+)\s*;")
USE_START = re.compile(r"^\s*(pub(?:\([^)]*\))?\s+)?use\s+")
FN_START = re.compile(r"^\s*(?:pub(?:\([^)]*\))?\s+)?(?:const\s+)?(?:async\s+)?(?:unsafe\s+)?fn\s+(\w+)")


def product_lines(path):
    """The file's lines before its test module (a `#[cfg(test)]` followed by `mod`)."""
    lines = path.read_text(encoding="utf-8").splitlines()
    for i, line in enumerate(lines):
        if TEST_MODULE.match(line) and i + 1 < len(lines) and re.match(r"^\s*mod\s+\w+", lines[i + 1]):
            return lines[:i]
    return lines


def is_test_file(path):
    return path.name in ("tests.rs", "test_database.rs") or "tests" in path.parts[path.parts.index("src") + 1:-1]


def modules(src, root_file):
    """Module path (tuple) -> file, for the files a crate root reaches by `mod x;` declarations."""
    found = {(): root_file}
    stack = [((), root_file)]
    while stack:
        path, file = stack.pop()
        folder = file.parent if file.name in ("mod.rs", "lib.rs", "main.rs") else file.with_suffix("")
        for line in product_lines(file):
            m = MOD_DECL.match(line)
            if not m:
                continue
            name = m.group(1)
            for candidate in (folder / f"{name}.rs", folder / name / "mod.rs"):
                if candidate.exists() and not is_test_file(candidate):
                    found[path + (name,)] = candidate
                    stack.append((path + (name,), candidate))
                    break
    return found


def expand(tree):
    """`a::{b, c::{d, e}}` -> ['a::b', 'a::c::d', 'a::c::e'] (aliases dropped)."""
    tree = re.sub(r"\s+as\s+\w+", "", tree.strip())
    if "{" not in tree:
        return [tree] if tree else []
    head, rest = tree.split("{", 1)
    inner = rest[: rest.rfind("}")]
    parts, depth, current = [], 0, ""
    for ch in inner:
        if ch == "," and depth == 0:
            parts.append(current)
            current = ""
            continue
        depth += ch == "{"
        depth -= ch == "}"
        current += ch
    parts.append(current)
    out = []
    for part in parts:
        for leaf in expand(part):
            out.append(head + leaf if leaf != "self" else head.rstrip(":"))
    return out


def uses(lines):
    """(is_pub, path) for each `use` of a file, multi-line statements joined."""
    out, statement, is_pub = [], None, False
    for line in lines:
        if statement is None:
            m = USE_START.match(line)
            if not m:
                continue
            is_pub = bool(m.group(1))
            statement = line[m.end():]
        else:
            statement += " " + line.strip()
        if ";" in statement:
            for path in expand(statement.split(";", 1)[0]):
                out.append((is_pub, path))
            statement = None
    return out


def absolute(module, path):
    """A use path from `module` as a path from the crate root, or None outside the crate."""
    parts = [p for p in path.split("::") if p]
    if not parts:
        return None
    base = list(module)
    if parts[0] == "crate":
        base, parts = [], parts[1:]
    elif parts[0] == "self":
        parts = parts[1:]
    elif parts[0] == "super":
        while parts and parts[0] == "super":
            base, parts = base[:-1], parts[1:]
    else:
        return None
    return tuple(base + parts)


class Crate:
    def __init__(self, name, src, root_file):
        self.name, self.src = name, src
        self.mods = modules(src, root_file)
        self.file_mod = {f: m for m, f in self.mods.items()}
        self.uses = {f: uses(product_lines(f)) for f in self.mods.values()}
        # Names a module hands on with `pub use`: (module, name) -> absolute path of the name.
        self.reexports = {}
        for f, items in self.uses.items():
            for is_pub, path in items:
                target = absolute(self.file_mod[f], path)
                if is_pub and target and target[-1] != "*":
                    self.reexports[(self.file_mod[f], target[-1])] = target

    def file_of(self, target, seen=0):
        """The file that defines the item (or module) at `target`."""
        for cut in range(len(target), -1, -1):
            module = target[:cut]
            if module in self.mods:
                if cut < len(target) and (module, target[cut]) in self.reexports and seen < 8:
                    via = self.reexports[(module, target[cut])]
                    if via != target:
                        return self.file_of(via + target[cut + 1:], seen + 1)
                return self.mods[module]
        return None

    def edges(self):
        """file -> {file it imports: [names]}; a module's re-exports of its own descendants are
        its face, not a dependency."""
        out = {}
        for f, items in self.uses.items():
            here = self.file_mod[f]
            for is_pub, path in items:
                target = absolute(here, path)
                if not target:
                    continue
                if is_pub and target[: len(here)] == here and len(target) > len(here):
                    continue
                to = self.file_of(target)
                if to and to != f:
                    out.setdefault(f, {}).setdefault(to, []).append(target[-1])
        return out


def circles(edges):
    """Strongly connected components of more than one file (Tarjan)."""
    index, low, stack, on, out, counter = {}, {}, [], set(), [], [0]

    def visit(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in edges.get(v, {}):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                out.append(sorted(component))

    sys.setrecursionlimit(10_000)
    for v in list(edges):
        if v not in index:
            visit(v)
    return out


def declared_layers(lib):
    text = "\n".join(line[3:].strip() for line in lib.read_text(encoding="utf-8").splitlines() if line.startswith("//!"))
    m = re.search(r"Layers, from the top down:\s*(.+?)(?:\.\s|\.$|\n\n)", text, re.S)
    if not m:
        return None
    floors = [[name.strip().strip("`") for name in floor.split(",") if name.strip()] for floor in m.group(1).replace("\n", " ").split("|")]
    return {name: i for i, floor in enumerate(floors) for name in floor}


def functions(path):
    """(name, first line, lines) of each function before the test module."""
    lines = product_lines(path)
    out, i = [], 0
    while i < len(lines):
        m = FN_START.match(lines[i])
        if not m:
            i += 1
            continue
        depth, started, j = 0, False, i
        while j < len(lines):
            code = re.sub(r'"(\\.|[^"\\])*"|//.*$', "", lines[j])
            code = re.sub(r"'(\\.|[^'\\])'", "", code)
            if not started and code.rstrip().endswith(";") and "{" not in code:
                break  # a declaration without a body
            depth += code.count("{") - code.count("}")
            started = started or "{" in code
            if started and depth <= 0:
                out.append((m.group(1), i + 1, j - i + 1))
                break
            j += 1
        i += 1
    return out


def allowed():
    out = {}
    if ALLOW.exists():
        for line in ALLOW.read_text(encoding="utf-8").splitlines():
            line = line.strip()
            if line and not line.startswith("#"):
                key, _, why = line.partition(" ")
                if not why.strip():
                    sys.exit(f"fence: {ALLOW}: `{key}` says no reason")
                out[key] = why.strip()
    return out


def main():
    root = Path(sys.argv[1] if len(sys.argv) > 1 else ".").resolve()
    import os

    os.chdir(root)
    failures, files, fns, edges_total, circle_total, back_up = [], 0, 0, 0, 0, 0
    allow, used_allow, longest_file, longest_fn = allowed(), set(), (0, ""), (0, "")
    for name in CRATES:
        src = Path(name) / "src"
        for root_name in ("lib.rs", "main.rs"):
            root_file = src / root_name
            if not root_file.exists():
                continue
            crate = Crate(name, src, root_file)
            edges = crate.edges()
            edges_total += sum(len(v) for v in edges.values())
            for component in circles(edges):
                circle_total += 1
                ties = [f"{a} -> {b}: {', '.join(sorted(set(n)))}" for a in component for b, n in edges.get(a, {}).items() if b in component]
                failures.append(f"import circle in {name} ({root_name}): " + "; ".join(ties))
            layers = declared_layers(root_file) if root_name == "lib.rs" else None
            if layers:
                for a, targets in edges.items():
                    top_a = crate.file_mod[a][:1]
                    for b, names in targets.items():
                        top_b = crate.file_mod[b][:1]
                        if top_a and top_b and top_a != top_b and top_a[0] in layers and top_b[0] in layers:
                            if layers[top_a[0]] > layers[top_b[0]]:
                                back_up += 1
                                failures.append(f"import back up a floor in {name}: {a} -> {b} ({', '.join(sorted(set(names)))}); the layers in {root_file} put `{top_b[0]}` above `{top_a[0]}`")
            if root_name == "lib.rs" and not layers:
                print(f"fence: {name}: lib.rs declares no layers (only circles are checked)")
        for path in sorted(src.rglob("*.rs")):
            if is_test_file(path) or name in NOT_PRODUCT:
                continue
            files += 1
            count = len(product_lines(path))
            longest_file = max(longest_file, (count, str(path)))
            if count > MAX_FILE_LINES:
                failures.append(f"{path}: {count} lines before its test module (at most {MAX_FILE_LINES})")
            for fn, line, length in functions(path):
                fns += 1
                key = f"{path}::{fn}"
                longest_fn = max(longest_fn, (length, f"{key} (line {line})") if key not in allow else longest_fn)
                if length > MAX_FN_LINES:
                    if key in allow:
                        used_allow.add(key)
                    else:
                        failures.append(f"{key} (line {line}): {length} lines (at most {MAX_FN_LINES}; or list it in {ALLOW} with why)")
    for key in sorted(set(allow) - used_allow):
        failures.append(f"{ALLOW}: `{key}` is no longer over {MAX_FN_LINES} lines (or gone): take it off the list")
    print(
        f"fence: {len(CRATES)} crates, {files} product files (not {', '.join(sorted(NOT_PRODUCT))}), {edges_total} imports between files, "
        f"{circle_total} import circles, {back_up} imports back up a floor; longest file "
        f"{longest_file[0]} lines ({longest_file[1]}, limit {MAX_FILE_LINES}); {fns} functions, "
        f"longest outside the allow-list {longest_fn[0]} lines ({longest_fn[1]}, limit {MAX_FN_LINES}); "
        f"{len(used_allow)} allowed over the limit"
    )
    for failure in failures:
        print(f"fence: FAIL {failure}")
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
