#!/usr/bin/env python3
"""Check every relative link of the repository's Markdown: README.md, docs/ and examples/.

A link to a file must name one that exists; a link with an anchor (`file.md#heading`, or
`#heading` in the same file) must name a heading of that file, slugged as GitHub and mdBook
slug them (lower case, punctuation but `-` and `_` dropped, spaces to `-`). Links to the web
(`http:`, `https:`, `mailto:`) are not fetched: CI has no network to check them on.

Exit 0 when every link resolves, 1 with one line per broken link (`file:line: target: why`).
"""
import os
import re
import sys

ROOT = os.path.normpath(os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))
LINK = re.compile(r"!?\[(?:[^\]\[]|\[[^\]]*\])*\]\(([^)\s]+)(?:\s+\"[^\"]*\")?\)")


def markdown_files():
    yield os.path.join(ROOT, "README.md")
    for top in ("docs", "examples"):
        for base, dirs, files in os.walk(os.path.join(ROOT, top)):
            dirs[:] = [d for d in dirs if d not in ("book", "target", "node_modules")]
            for f in files:
                if f.endswith(".md"):
                    yield os.path.join(base, f)


def slug(heading):
    text = re.sub(r"<[^>]+>", "", heading).strip().lower()
    text = re.sub(r"[^\w\- ]", "", text)
    return text.replace(" ", "-")


def anchors(path, cache={}):
    if path not in cache:
        found, code = set(), False
        with open(path, encoding="utf-8") as f:
            for line in f:
                if line.startswith("```"):
                    code = not code
                elif not code and re.match(r"^#{1,6} ", line):
                    s = slug(line.lstrip("#").strip())
                    n, candidate = 1, s
                    while candidate in found:
                        candidate = f"{s}-{n}"
                        n += 1
                    found.add(candidate)
        cache[path] = found
    return cache[path]


def links(path):
    code = False
    with open(path, encoding="utf-8") as f:
        for number, line in enumerate(f, 1):
            if line.startswith("```"):
                code = not code
                continue
            if code:
                continue
            # Inline code is not a link.
            for m in LINK.finditer(re.sub(r"`[^`]*`", "", line)):
                yield number, m.group(1)


def check(path):
    for number, target in links(path):
        if re.match(r"^(https?:|mailto:)", target):
            continue
        file, _, anchor = target.partition("#")
        dest = os.path.normpath(os.path.join(os.path.dirname(path), file)) if file else path
        where = f"{os.path.relpath(path, ROOT)}:{number}: {target}"
        if not os.path.exists(dest):
            yield f"{where}: no such file"
        elif anchor and dest.endswith(".md") and anchor not in anchors(dest):
            yield f"{where}: no heading #{anchor} in {os.path.relpath(dest, ROOT)}"


def main():
    broken = [b for p in sorted(markdown_files()) for b in check(p)]
    for b in broken:
        print(b)
    print(f"check_links: {len(broken)} broken link(s)", file=sys.stderr)
    return 1 if broken else 0


if __name__ == "__main__":
    sys.exit(main())
