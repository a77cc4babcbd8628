#!/usr/bin/env python3
"""Import cycles between the modules of a crate: host-sim, core or firmware (standard library only).

    python3 scripts/module_cycles.py [--src host-sim/src] [--no-tests] [--level leaf|top|both] [--edges]
    python3 scripts/module_cycles.py --all     # core, firmware and host-sim, each in turn

Builds the module tree of the library (from lib.rs) and of the binary (from main.rs) by
following their `mod name;` declarations, then reads every file's paths into the crate:
`use` trees and inline paths starting with `crate::`, `super::`, `self::`, a file-backed
child module (`cli::...` in main.rs) and, in the binary, the library's name (`harmonic_sim::`,
read from the crate's Cargo.toml). Comments (doc
links included) and string literals are ignored. A path counts as a dependency on the deepest
file-backed module it names (`crate::run::sim::Report` -> `run::sim`); inline modules such as
`mod tests` belong to their file.

Two graphs are checked:
- leaf: one node per file (`world/mod.rs` is `world`, `run/sim.rs` is `run::sim`);
- top: one node per top-level module of the crate (`run`, `world`, ...; the binary's files
  are `[bin] main` and `[bin] cli`), edges inside one top-level module dropped.

A cycle is a strongly connected set of more than one node; for each, the shortest cycle
through every edge in it is printed with the lines that make the edges. Edges made only by
`#[cfg(test)]` code are marked `(test)`; `--no-tests` leaves them out.

Prints "no cycles" and exits 0, or lists the cycles and exits 1.
"""
import argparse
import os
import re
import sys
from collections import defaultdict, deque

# ---------------------------------------------------------------------------------------------
# Lexing: blank out comments, strings and char literals, keeping offsets and line numbers.


def strip(src):
    out = list(src)
    i, n = 0, len(src)

    def blank(a, b):
        for k in range(a, b):
            if out[k] != "\n":
                out[k] = " "

    while i < n:
        c = src[i]
        if src.startswith("//", i):
            j = src.find("\n", i)
            j = n if j < 0 else j
            blank(i, j)
            i = j
        elif src.startswith("/*", i):
            depth, j = 1, i + 2
            while j < n and depth:
                if src.startswith("/*", j):
                    depth, j = depth + 1, j + 2
                elif src.startswith("*/", j):
                    depth, j = depth - 1, j + 2
                else:
                    j += 1
            blank(i, j)
            i = j
        elif (m := re.compile(r'b?r(#*)"').match(src, i)) and (i == 0 or not (src[i - 1].isalnum() or src[i - 1] == "_")):
            end = src.find('"' + m.group(1), m.end())
            j = n if end < 0 else end + 1 + len(m.group(1))
            blank(i, j)
            i = j
        elif c == '"' or (c == "b" and src.startswith('b"', i) and (i == 0 or not (src[i - 1].isalnum() or src[i - 1] == "_"))):
            j = i + (2 if c == "b" else 1)
            while j < n and src[j] != '"':
                j += 2 if src[j] == "\\" else 1
            blank(i, j + 1)
            i = j + 1
        elif c == "'":
            # A char literal ('a', '\n', '\u{1F600}', '{') or a lifetime ('a, 'static).
            if i + 1 < n and src[i + 1] == "\\":
                j = src.find("'", i + 2)
                j = n if j < 0 else j
                blank(i, j + 1)
                i = j + 1
            elif i + 2 < n and src[i + 2] == "'":
                blank(i, i + 3)
                i += 3
            else:
                i += 1
        else:
            i += 1
    return "".join(out)


# ---------------------------------------------------------------------------------------------
# The module tree.

MOD_DECL = re.compile(r"(?P<attrs>(?:#\[[^\]]*\]\s*)*)(?:pub(?:\s*\([^)]*\))?\s+)?mod\s+(?P<name>\w+)\s*(?P<end>[;{])")


class File:
    def __init__(self, crate, segs, path, test):
        self.crate, self.segs, self.path, self.test = crate, tuple(segs), path, test
        self.text = strip(open(path, encoding="utf-8").read())
        self.children = {}  # name -> File (file-backed child modules)
        self.inline = []  # (start, end, name, test): inline `mod name { ... }` blocks

    @property
    def leaf(self):
        name = "::".join(self.segs)
        if self.crate == "bin":
            return "[bin] " + (name or "main")
        return name or "crate (lib.rs)"

    @property
    def top(self):
        if self.crate == "bin":
            return "[bin] " + (self.segs[0] if self.segs else "main")
        return self.segs[0] if self.segs else "crate (lib.rs)"

    def line(self, pos):
        return self.text.count("\n", 0, pos) + 1


def matching_brace(text, open_pos):
    depth = 0
    for k in range(open_pos, len(text)):
        if text[k] == "{":
            depth += 1
        elif text[k] == "}":
            depth -= 1
            if depth == 0:
                return k
    return len(text)


def load(crate, segs, path, test, files):
    f = File(crate, segs, path, test)
    files.append(f)
    base = os.path.dirname(path)
    stem = os.path.splitext(os.path.basename(path))[0]
    if stem not in ("lib", "main", "mod"):
        base = os.path.join(base, stem)
    for m in MOD_DECL.finditer(f.text):
        is_test = "cfg(test)" in re.sub(r"\s", "", m.group("attrs"))
        name = m.group("name")
        if m.group("end") == "{":
            open_pos = m.end() - 1
            f.inline.append((open_pos, matching_brace(f.text, open_pos), name, is_test))
            continue
        if any(a <= m.start() <= b for a, b, _, _ in f.inline):
            continue  # `mod x;` inside an inline module: not used in this crate
        for cand in (os.path.join(base, name + ".rs"), os.path.join(base, name, "mod.rs")):
            if os.path.exists(cand):
                f.children[name] = load(crate, list(segs) + [name], cand, test or is_test, files)
                break
    return f


# ---------------------------------------------------------------------------------------------
# Paths.

TOKEN = re.compile(r"\s*(::|[{},*]|\w+)")


def use_paths(tree):
    """Expands a use tree (`a::b::{self, c::D, e::*}`) into paths (lists of segments)."""
    toks = TOKEN.findall(tree)
    pos = 0

    def parse(prefix):
        nonlocal pos
        paths, segs = [], list(prefix)
        while pos < len(toks):
            t = toks[pos]
            if t == "{":
                pos += 1
                while pos < len(toks) and toks[pos] != "}":
                    if toks[pos] == ",":
                        pos += 1
                        continue
                    paths += parse(segs)
                pos += 1
                return paths
            if t in (",", "}"):
                break
            if t == "::":
                pos += 1
                continue
            if t == "as":
                pos += 2
                continue
            if t != "self" or not segs:
                segs.append(t)
            pos += 1
        paths.append(segs)
        return paths

    out = []
    while pos < len(toks):
        if toks[pos] == ",":
            pos += 1
            continue
        out += parse([])
    return out


USE = re.compile(r"\buse\s+([^;]+);")
INLINE_PATH = re.compile(r"(?<![\w:$])(\w+)((?:\s*::\s*\w+)+)")


def module_at(f, pos):
    """The full module path at `pos` in file `f` (file segments plus enclosing inline modules)."""
    segs, test = list(f.segs), f.test
    for start, end, name, is_test in sorted(f.inline):
        if start < pos <= end:
            segs.append(name)
            test = test or is_test
    return segs, test


LIB_NAME = "harmonic_sim"


def resolve(f, pos, segs, roots):
    """The file-backed module a path written at `pos` in `f` names, or None (external)."""
    here, _ = module_at(f, pos)
    crate = f.crate
    first = segs[0]
    if first == "crate":
        absolute, rest = [], segs[1:]
    elif first == LIB_NAME and f.crate == "bin":
        crate, absolute, rest = "lib", [], segs[1:]
    elif first in ("self", "super"):
        absolute, rest = list(here), list(segs)
        while rest and rest[0] in ("self", "super"):
            if rest.pop(0) == "super":
                absolute = absolute[:-1]
    elif len(here) == len(f.segs) and first in f.children:
        absolute, rest = list(here), list(segs)
    else:
        return None
    node = roots[crate]
    for s in absolute + rest:
        if s not in node.children:
            break  # an item, or an inline module of node's file
        node = node.children[s]
    return node


# ---------------------------------------------------------------------------------------------
# Graphs.


def sccs(nodes, edges):
    index, low, on, stack, out, counter = {}, {}, set(), [], [], [0]

    def visit(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in sorted(edges[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    sys.setrecursionlimit(10000)
    for v in sorted(nodes):
        if v not in index:
            visit(v)
    return sorted(out)


def shortest_path(edges, comp, a, b):
    prev, queue = {a: None}, deque([a])
    while queue:
        v = queue.popleft()
        if v == b:
            break
        for w in sorted(edges[v]):
            if w in comp and w not in prev:
                prev[w] = v
                queue.append(w)
    path, v = [], b
    while v is not None:
        path.append(v)
        v = prev[v]
    return path[::-1]


def report(title, nodes, evidence):
    edges = defaultdict(set)
    for (a, b) in evidence:
        edges[a].add(b)
    comps = sccs(nodes, edges)
    print(f"{title}: {len(nodes)} modules, {len(evidence)} edges, ", end="")
    if not comps:
        print("no cycles")
        return 0
    print(f"{len(comps)} cycle{'s' if len(comps) > 1 else ''}")
    for comp in comps:
        members = set(comp)
        print(f"  strongly connected: {', '.join(comp)}")
        seen = set()
        for a in comp:
            for b in sorted(edges[a] & members):
                cycle = [a] + shortest_path(edges, members, b, a)
                k = cycle[:-1]
                key = min(tuple(k[i:] + k[:i]) for i in range(len(k)))
                if key in seen:
                    continue
                seen.add(key)
                print("    cycle: " + " -> ".join(cycle))
                for x, y in zip(cycle, cycle[1:]):
                    refs = evidence[(x, y)]
                    tag = " (test)" if all(t for _, _, t in refs) else ""
                    where, text, _ = refs[0]
                    more = f" (+{len(refs) - 1} more)" if len(refs) > 1 else ""
                    print(f"      {x} -> {y}{tag}: {where}: {text}{more}")
    return 1


def crate_name(src):
    """The library's name as paths in the binary spell it, from the crate's Cargo.toml."""
    manifest = os.path.join(os.path.dirname(src), "Cargo.toml")
    try:
        text = open(manifest, encoding="utf-8").read()
    except OSError:
        return LIB_NAME
    m = re.search(r'^name\s*=\s*"([^"]+)"', text, re.M)
    return m.group(1).replace("-", "_") if m else LIB_NAME


def check(src, args):
    global LIB_NAME
    src = os.path.normpath(src)
    LIB_NAME = crate_name(src)
    rel = os.path.dirname(os.path.dirname(src)) or "."

    files, roots = [], {}
    for crate, root in (("lib", "lib.rs"), ("bin", "main.rs")):
        if os.path.exists(os.path.join(src, root)):
            roots[crate] = load(crate, [], os.path.join(src, root), False, files)

    leaf, top = defaultdict(list), defaultdict(list)
    for f in files:
        lines = open(f.path, encoding="utf-8").read().split("\n")
        found = []
        for m in USE.finditer(f.text):
            for segs in use_paths(m.group(1)):
                if segs:
                    found.append((m.start(1), segs))
        uses = [(m.start(), m.end()) for m in USE.finditer(f.text)]
        for m in INLINE_PATH.finditer(f.text):
            if not any(a <= m.start() < b for a, b in uses):
                found.append((m.start(), [m.group(1)] + re.findall(r"\w+", m.group(2))))
        for pos, segs in found:
            target = resolve(f, pos, segs, roots)
            if target is None or target is f:
                continue
            _, test = module_at(f, pos)
            if test and args.no_tests:
                continue
            line = f.line(pos)
            text = lines[line - 1].strip()
            ref = (f"{os.path.relpath(f.path, rel)}:{line}", text, test)
            leaf[(f.leaf, target.leaf)].append(ref)
            if f.top != target.top:
                top[(f.top, target.top)].append(ref)

    if args.edges:
        for name, graph in (("leaf", leaf), ("top", top)):
            for (a, b), refs in sorted(graph.items()):
                tag = " (test)" if all(t for _, _, t in refs) else ""
                print(f"{name}: {a} -> {b}{tag} [{len(refs)}]")
    status = 0
    if args.level in ("leaf", "both"):
        status |= report("leaf modules (files)", {f.leaf for f in files}, leaf)
    if args.level in ("top", "both"):
        status |= report("top-level modules", {f.top for f in files}, top)
    return status


def main():
    here = os.path.dirname(os.path.abspath(__file__))
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--src", default=os.path.join(here, "..", "host-sim", "src"))
    ap.add_argument("--all", action="store_true", help="check core, firmware and host-sim")
    ap.add_argument("--no-tests", action="store_true", help="ignore #[cfg(test)] code")
    ap.add_argument("--level", choices=["leaf", "top", "both"], default="both")
    ap.add_argument("--edges", action="store_true", help="also print every edge of the graphs")
    args = ap.parse_args()
    crates = ["core", "firmware", "host-sim"] if args.all else [None]
    status = 0
    for crate in crates:
        src = os.path.join(here, "..", crate, "src") if crate else args.src
        if crate:
            print(f"{crate}:")
        status |= check(src, args)
    if status == 0:
        print("no cycles")
    return status


if __name__ == "__main__":
    sys.exit(main())
