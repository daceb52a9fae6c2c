#!/usr/bin/env python3
"""The crate's layers: every import must point down the layer table.

    python3 tools/layers.py            # check; exit 1 on an import that points up and is not
                                       # in the ratchet (tools/layers-allowed.txt)
    python3 tools/layers.py --graph    # also print every module's imports, by layer
    python3 tools/layers.py --bless    # rewrite the ratchet from today's code (it may only
                                       # shrink: a new line there is a review question)

The layer of each top-level module of src/ is LAYERS below (the design chapter of the docs
shows the same table). A file imports a module when it names `crate::<module>` in a `use`
line or in a path. An import of a module of a *higher* layer points up: that is what makes
an import circle possible, and what a reader cannot follow. Imports between modules of the
same layer, and between the files of one folder, are allowed in one direction only: a circle
among them is reported too.

The ratchet lists the upward imports the code still has while the house is being moved to
this table; the check fails on any upward import not listed, and on a listed one that is gone
(so the list shrinks with the code instead of going stale).
"""
import os
import re
import sys
from collections import defaultdict

LAYERS = [
    ("foundations", ["error", "hash", "linalg", "runner", "output"]),
    ("one run's mathematics", ["model", "scenario", "sim", "filter", "metrics", "analysis", "step_loop", "sequential"]),
    ("exchange", ["exchange", "score"]),
    ("plugin API", ["system", "trial", "prelude"]),
    ("built-in systems", ["systems"]),
    ("experiment", ["experiment"]),
    ("commands", ["study", "simulate", "merge", "power", "tune", "check", "ulog"]),
    ("presentation", ["plot", "report"]),
    ("front ends", ["cli"]),
]
LAYER_OF = {m: i for i, (_, mods) in enumerate(LAYERS) for m in mods}

ROOT = os.path.normpath(os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))
SRC = os.path.join(ROOT, "src")
ALLOWED = os.path.join(ROOT, "tools", "layers-allowed.txt")

PATH_RE = re.compile(r"\bcrate::([a-z_][a-z0-9_]*)")
USE_TREE_RE = re.compile(r"\buse\s+crate::\{([^;]*)\};", re.S)


def strip_comments(text):
    text = re.sub(r"/\*.*?\*/", "", text, flags=re.S)
    return "\n".join(line.split("//")[0] for line in text.split("\n"))


def cut_tests(text):
    """Unit-test modules may import anything they test against."""
    i = text.find("#[cfg(test)]")
    return text if i < 0 else text[:i]


def module_of(rel):
    first = rel.split(os.sep)[0]
    return first[:-3] if first.endswith(".rs") else first


def imports():
    """(file, module, imported module) for every crate-internal import."""
    out = []
    for dirpath, _, names in os.walk(SRC):
        for n in sorted(names):
            if not n.endswith(".rs"):
                continue
            path = os.path.join(dirpath, n)
            rel = os.path.relpath(path, SRC)
            if rel in ("lib.rs", "main.rs"):
                continue
            mod = module_of(rel)
            text = cut_tests(strip_comments(open(path, encoding="utf-8").read()))
            found = set(PATH_RE.findall(text))
            for tree in USE_TREE_RE.findall(text):
                for item in tree.split(","):
                    head = item.strip().split("::")[0].strip()
                    if head and head != "self":
                        found.add(head)
            for other in sorted(found):
                if other != mod and other in LAYER_OF:
                    out.append((rel, mod, other))
    return out


def circles(edges):
    """Strongly connected components of more than one module (Tarjan)."""
    graph = defaultdict(set)
    for a, b in edges:
        graph[a].add(b)
    index, low, stack, on, comps, counter = {}, {}, [], set(), [], [0]

    def visit(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in graph[v]:
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
                comps.append(sorted(comp))

    for v in list(graph):
        if v not in index:
            visit(v)
    return comps


def folder_edges():
    """Imports between the files of each folder module: (folder, file, file) from `super::x`
    inside the folder and `crate::folder::x` paths."""
    out = set()
    for folder in sorted(os.listdir(SRC)):
        base = os.path.join(SRC, folder)
        if not os.path.isdir(base):
            continue
        children = {n[:-3] if n.endswith(".rs") else n for n in os.listdir(base) if n != "mod.rs"}
        for dirpath, _, names in os.walk(base):
            for n in names:
                if not n.endswith(".rs"):
                    continue
                rel = os.path.relpath(os.path.join(dirpath, n), base)
                first = rel.split(os.sep)[0]
                me = "mod" if rel == "mod.rs" else (first[:-3] if first.endswith(".rs") else first)
                text = cut_tests(strip_comments(open(os.path.join(dirpath, n), encoding="utf-8").read()))
                names_ = set(re.findall(r"\bcrate::" + folder + r"::([a-z_][a-z0-9_]*)", text))
                if os.sep not in rel:
                    names_ |= set(re.findall(r"\bsuper::([a-z_][a-z0-9_]*)", text))
                for tree in re.findall(r"\buse\s+(?:super|crate::" + folder + r")::\{([^;]*)\};", text, re.S):
                    for item in tree.split(","):
                        names_.add(item.strip().split("::")[0].strip())
                for o in names_:
                    if o in children and o != me and me != "mod":
                        out.add((folder, me, o))
    return out


def main():
    args = sys.argv[1:]
    unknown = sorted({module_of(os.path.relpath(os.path.join(d, n), SRC))
                      for d, _, ns in os.walk(SRC) for n in ns
                      if n.endswith(".rs") and os.path.relpath(os.path.join(d, n), SRC) not in ("lib.rs", "main.rs")}
                     - set(LAYER_OF))
    if unknown:
        print(f"modules without a layer (add them to LAYERS in tools/layers.py): {', '.join(unknown)}")
        return 1
    found = imports()
    up = sorted({f"{rel}: {mod} ({LAYERS[LAYER_OF[mod]][0]}) -> {other} ({LAYERS[LAYER_OF[other]][0]})"
                 for rel, mod, other in found if LAYER_OF[other] > LAYER_OF[mod]})
    edges = {(m, o) for _, m, o in found}
    if "--graph" in args:
        for i, (name, mods) in enumerate(LAYERS):
            print(f"{i + 1}. {name}")
            for m in mods:
                targets = sorted({o for a, o in edges if a == m}, key=lambda o: (LAYER_OF[o], o))
                if any(a == m for a, _ in edges) or m in {o for _, o in edges}:
                    print(f"     {m} -> {', '.join(targets) if targets else '(nothing)'}")
    comps = [" <-> ".join(c) for c in circles(edges)]
    inner = folder_edges()
    for folder in sorted({f for f, _, _ in inner}):
        comps += [f"{folder}: " + " <-> ".join(c)
                  for c in circles({(a, b) for f, a, b in inner if f == folder})]
    up += [f"circle: {c}" for c in comps]
    if "--bless" in args:
        with open(ALLOWED, "w", encoding="utf-8") as f:
            f.write("# Upward imports the code still has (tools/layers.py). This list only shrinks.\n")
            for line in up:
                f.write(line + "\n")
        print(f"{len(up)} upward imports written to {os.path.relpath(ALLOWED, ROOT)}")
        return 0
    allowed = set()
    if os.path.exists(ALLOWED):
        allowed = {l.strip() for l in open(ALLOWED, encoding="utf-8") if l.strip() and not l.startswith("#")}
    new = [u for u in up if u not in allowed]
    gone = sorted(allowed - set(up))
    print(f"{len(LAYER_OF)} modules in {len(LAYERS)} layers; {len(edges)} imports between modules; "
          f"{len(up) - len(comps)} point up; {len(comps)} circle(s); {len(up) - len(new)} of these in the ratchet")
    status = 0
    if new:
        status = 1
        print("imports that point up or close a circle (a module may import only from the layers below it):")
        for u in new:
            print("  " + u)
    if gone:
        status = 1
        print("gone from the code, remove from tools/layers-allowed.txt (python3 tools/layers.py --bless):")
        for g in gone:
            print("  " + g)
    return status


if __name__ == "__main__":
    sys.exit(main())
