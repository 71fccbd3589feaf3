"""Checks of the code's shape a reviewer can repeat (issue 33), run by scripts/test.sh:

1. no import loops: within every crate of the workspace, no two sibling modules (files or
   directories of one parent) that use each other, directly or round a longer circle (a
   child's `super::` and a parent's `mod child` are containment, not a loop);
2. no sleeping to wait for a state: no `sleep(` (a fixed nap; `sleep_until` a deadline is a
   timer) inside a loop of the vehicle node or its MAVLink bridge;
3. no struct's field list written out twice: no two structs of a crate that share most of
   their fields (a mirror kept by hand; a struct that only serialises, the wire or page view
   of another, is its encoding and is not counted), and no function that copies a struct
   field by field (`self.a = c.a.clone(); self.b = c.b.clone(); ...`).

4. functions a reader can hold: no function (tests aside) of more than 80 lines unless its
   doc comment says why, in a sentence that begins "Long because".

5. impls a reader can hold: no impl block (tests aside) of more than 25 methods or 600 lines
   unless its doc comment says why, in a sentence that begins "Wide because".

The crates are the workspace's members (Cargo.toml), so a new crate is checked as it lands.
scripts/test_check_structure.py plants each kind of problem in a scratch tree and sees it found.

Prints what it finds, one line each, and exits 1 if anything is found.
usage: python3 scripts/check_structure.py [repo root]
"""
import os
import re
import sys
import tomllib

ROOT = os.path.abspath(sys.argv[1] if len(sys.argv) > 1 else os.path.join(os.path.dirname(__file__), ".."))
problems = []


def rust_files(crate_src):
    for dirpath, _, files in os.walk(crate_src):
        for f in sorted(files):
            if f.endswith(".rs"):
                yield os.path.join(dirpath, f)


def strip_comments(text):
    text = re.sub(r"/\*.*?\*/", "", text, flags=re.S)
    return "\n".join(re.sub(r"//.*", "", line) for line in text.split("\n"))


def module_path(crate_src, path):
    """The module path of a file: src/lib.rs -> [], src/a/mod.rs -> [a], src/a/b.rs -> [a, b]."""
    rel = os.path.relpath(path, crate_src)[:-3].split(os.sep)
    if rel[-1] in ("lib", "main", "mod"):
        rel = rel[:-1]
    return rel


# 1. Import loops among sibling modules.
def check_loops(crate):
    src = os.path.join(ROOT, crate, "src")
    files = [f for f in rust_files(src) if "/bin/" not in f and not f.endswith("main.rs")]
    modules = {tuple(module_path(src, f)): f for f in files}

    def resolve(parts):
        for k in range(len(parts), 0, -1):
            if tuple(parts[:k]) in modules:
                return tuple(parts[:k])
        return None

    edges = {}
    for mod, f in modules.items():
        text = strip_comments(open(f).read())
        text = text.split("#[cfg(test)]")[0]
        for m in re.finditer(r"\b(crate|super)((?:::\w+)+)", text):
            parts = m.group(2).split("::")[1:]
            base = list(mod) if os.path.basename(f) == "mod.rs" or not mod else list(mod[:-1])
            if m.group(1) == "crate":
                target = resolve(parts)
            else:
                target = resolve(base[:-1] + parts) if os.path.basename(f) == "mod.rs" else resolve(base + parts)
            if target is None or target == mod:
                continue
            # Lift both to the children of their common ancestor; an ancestor is containment.
            k = 0
            while k < min(len(mod), len(target)) and mod[k] == target[k]:
                k += 1
            if k == len(target) or k == len(mod):
                continue
            a, b = mod[: k + 1], target[: k + 1]
            edges.setdefault(a, {}).setdefault(b, f"{os.path.relpath(f, ROOT)}: {m.group(0)}")
    # Cycles: strongly connected components of more than one module.
    index, low, stack, on, sccs, counter = {}, {}, [], set(), [], [0]

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
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                sccs.append(comp)

    for v in list(edges):
        if v not in index:
            visit(v)
    for comp in sccs:
        names = sorted("::".join(c) for c in comp)
        why = [edges[a][b] for a in comp for b in edges.get(a, {}) if b in comp]
        problems.append(f"import loop in {crate}/: {' <-> '.join(names)} ({'; '.join(sorted(why))})")


# 2. Sleeping in a loop in the vehicle node and the bridge.
def check_sleeps(paths):
    for base in paths:
        if not os.path.exists(os.path.join(ROOT, base)):
            continue
        for f in rust_files(os.path.join(ROOT, base)) if os.path.isdir(os.path.join(ROOT, base)) else [os.path.join(ROOT, base)]:
            text = strip_comments(open(f).read()).split("#[cfg(test)]")[0]
            depth, loops = 0, []
            for n, line in enumerate(text.split("\n"), 1):
                if re.search(r"\b(loop|while|for)\b[^;]*\{\s*$", line) or re.search(r"\bloop\s*\{", line):
                    loops.append(depth)
                if loops and re.search(r"\bsleep\s*\(", line):
                    problems.append(f"{os.path.relpath(f, ROOT)}:{n}: sleep inside a loop: {line.strip()}")
                depth += line.count("{") - line.count("}")
                while loops and depth <= loops[-1]:
                    loops.pop()


def block(text, start):
    """The text of the block that opened just before `start`, up to its closing brace."""
    depth = 1
    for i in range(start, len(text)):
        depth += {"{": 1, "}": -1}.get(text[i], 0)
        if depth == 0:
            return text[start:i]
    return text[start:]


# 3. Field lists written out twice.
STRUCT = re.compile(r"((?:#\[[^\]]*\]\s*)*)(?:pub(?:\([^)]*\))?\s+)?struct\s+(\w+)(?:<[^>]*>)?\s*\{(.*?)\n\}", re.S)


def check_field_lists(crates):
    for crate in crates:
        structs = {}
        for f in rust_files(os.path.join(ROOT, crate, "src")):
            text = strip_comments(open(f).read())
            for m in STRUCT.finditer(text):
                # A struct that only serialises (a wire or page view of another, as `FieldsWire`
                # is of `Fields`) is that other's encoding, not a second list kept by hand.
                derives = m.group(1)
                if "Serialize" in derives and "Deserialize" not in derives:
                    continue
                fields = re.findall(r"^\s*(?:pub(?:\([^)]*\))?\s+)?(\w+)\s*:", m.group(3), re.M)
                if len(fields) >= 5:
                    structs[m.group(2)] = (set(fields), os.path.relpath(f, ROOT))
            for fn in re.finditer(r"\bfn\s+(\w+)[^{;]*\{", text):
                body = block(text, fn.end())
                copied = set(re.findall(r"self\.(\w+)\s*=\s*\w+\.(\w+)", body))
                same = {a for a, b in copied if a == b}
                if len(same) >= 5:
                    problems.append(
                        f"{os.path.relpath(f, ROOT)}: fn {fn.group(1)} copies {len(same)} fields one by one "
                        f"({', '.join(sorted(same)[:5])}...): keep them in one value and copy that")
        names = sorted(structs)
        for i, a in enumerate(names):
            for b in names[i + 1:]:
                fa, fb = structs[a][0], structs[b][0]
                shared = fa & fb
                if len(shared) >= 5 and len(shared) >= 0.8 * min(len(fa), len(fb)):
                    problems.append(
                        f"{crate}/: structs {a} ({structs[a][1]}) and {b} ({structs[b][1]}) share "
                        f"{len(shared)} fields: one field list written twice")


def code_lines(crates):
    """Each non-test source file of `crates` with its lines before any `#[cfg(test)]` (the
    length and width rules are for the code, not its tests)."""
    for crate in crates:
        for f in rust_files(os.path.join(ROOT, crate, "src")):
            if f.endswith("/tests.rs"):
                continue
            lines = open(f).read().split("\n")
            test_from = next((i for i, l in enumerate(lines) if l.startswith("#[cfg(test)]")), len(lines))
            yield f, lines, test_from


def doc_says(lines, i, phrase):
    """Whether the doc comments and attributes above line `i` contain `phrase`."""
    k, doc = i - 1, []
    while k >= 0 and re.match(r"\s*(///|#\[)", lines[k]):
        doc.append(lines[k])
        k -= 1
    return phrase in " ".join(d.strip().lstrip("/ ") for d in reversed(doc))


# 4. Long functions.
def check_lengths(crates, limit=80):
    for f, lines, test_from in code_lines(crates):
        for i, line in enumerate(lines[:test_from]):
            m = re.match(r"\s*(?:pub(?:\([^)]*\))?\s+)?(?:async\s+)?fn\s+(\w+)", line)
            if not m:
                continue
            depth, started, end = 0, False, i
            for j in range(i, len(lines)):
                depth += lines[j].count("{") - lines[j].count("}")
                started = started or "{" in lines[j]
                if not started and lines[j].rstrip().endswith(";"):
                    break
                if started and depth <= 0:
                    end = j
                    break
            n = end - i + 1
            if n > limit and not doc_says(lines, i, "Long because"):
                problems.append(f"{os.path.relpath(f, ROOT)}:{i + 1}: fn {m.group(1)} is {n} lines "
                                f"(over {limit}; split it, or say why in its doc: \"Long because ...\")")


# 5. Wide impls.
def check_impls(crates, methods=25, limit=600):
    for f, lines, test_from in code_lines(crates):
        for i, line in enumerate(lines[:test_from]):
            if not re.match(r"impl\b.*\{\s*$", line):
                continue
            end = next((j for j in range(i + 1, len(lines)) if lines[j] == "}"), len(lines) - 1)
            fns = sum(1 for body in lines[i:end]
                      if re.match(r"    (?:pub(?:\([^)]*\))?\s+)?(?:const\s+)?(?:async\s+)?fn\s", body))
            n = end - i + 1
            if (fns > methods or n > limit) and not doc_says(lines, i, "Wide because"):
                problems.append(f"{os.path.relpath(f, ROOT)}:{i + 1}: {line.strip()[:-1].strip()} has {fns} "
                                f"methods in {n} lines (over {methods} or {limit}; split it by concern, or "
                                f"say why in its doc: \"Wide because ...\")")


def workspace_crates():
    """The workspace's members that have a `src/` (Cargo.toml's `[workspace] members`)."""
    with open(os.path.join(ROOT, "Cargo.toml"), "rb") as f:
        members = tomllib.load(f)["workspace"]["members"]
    return [m for m in members if os.path.isdir(os.path.join(ROOT, m, "src"))]


CRATES = workspace_crates()
for crate in CRATES:
    check_loops(crate)
check_sleeps(["vehicles/src/node", "vehicles/src/bridge"])
check_field_lists(CRATES)
check_lengths(CRATES)
check_impls(CRATES)
for p in problems:
    print(p)
print(f"check_structure: {len(problems)} problem(s)")
sys.exit(1 if problems else 0)
