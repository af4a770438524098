#!/usr/bin/env python3
"""The documentation's invariants: README.md has at most 250 lines (the user's page; the rest
lives in docs/), and every relative link in README.md and docs/*.md resolves: to a file or
directory of the tree and, where it names an anchor (#section) of a Markdown file, to one of that
file's headings as GitHub spells their anchors. Links in code blocks and code spans are text, not
links; links with a scheme (https:, mailto:) are not checked.

Usage: check_docs.py [ROOT]   (default: the repository holding this script)
Prints every problem as FILE:LINE: what is wrong, and exits 1 if there is one."""
import pathlib
import re
import sys

MAX_README_LINES = 250

# [text](target) and [text](target "title"); the text may hold code spans but no brackets.
INLINE_LINK = re.compile(r"\[[^\]]*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")
# [label]: target
REFERENCE_LINK = re.compile(r"^\s{0,3}\[[^\]]+\]:\s*<?(\S+?)>?(?:\s+.*)?$")
SCHEME = re.compile(r"^[A-Za-z][A-Za-z0-9+.-]*:")
HEADING = re.compile(r"^\s{0,3}(#{1,6})\s+(.*?)\s*#*\s*$")
FENCE = re.compile(r"^\s{0,3}(```|~~~)")


def outside_fences(text):
    """(line number, line) of the lines outside fenced code blocks."""
    fence = None
    for number, line in enumerate(text.split("\n"), start=1):
        match = FENCE.match(line)
        if fence is not None:
            if match and line.strip().startswith(fence):
                fence = None
            continue
        if match:
            fence = match.group(1)
            continue
        yield number, line


def prose_lines(text):
    """The lines outside fenced code blocks with their code spans blanked."""
    for number, line in outside_fences(text):
        yield number, re.sub(r"(`+)(.+?)\1", lambda m: " " * len(m.group(0)), line)


def github_anchor(heading):
    """GitHub's anchor of a heading: the text without markup (a code span keeps its text, a link
    its label), lower case, punctuation dropped, spaces to hyphens."""
    text = re.sub(r"\[([^\]]*)\]\([^)]*\)", r"\1", heading)
    text = text.replace("`", "").lower()
    text = re.sub(r"[^\w\- ]", "", text)
    return text.replace(" ", "-")


def file_anchors(path):
    """Every anchor of a Markdown file's headings; a repeated heading gets -1, -2, ... as on GitHub."""
    seen, result = {}, set()
    for _, line in outside_fences(path.read_text(encoding="utf-8")):
        heading = HEADING.match(line)
        if not heading:
            continue
        base = github_anchor(heading.group(2))
        count = seen.get(base, 0)
        seen[base] = count + 1
        result.add(base if count == 0 else f"{base}-{count}")
    return result


def links(path):
    for number, line in prose_lines(path.read_text(encoding="utf-8")):
        for match in INLINE_LINK.finditer(line):
            yield number, match.group(1)
        reference = REFERENCE_LINK.match(line)
        if reference:
            yield number, reference.group(1)


def check(root):
    root = root.resolve()
    problems = []
    readme = root / "README.md"
    if not readme.is_file():
        return [f"{readme}: no README.md"]
    lines = len(readme.read_text(encoding="utf-8").splitlines())
    if lines > MAX_README_LINES:
        problems.append(f"README.md: {lines} lines, at most {MAX_README_LINES} (move the rest into docs/)")
    pages = [readme] + sorted((root / "docs").glob("*.md"))
    for page in pages:
        name = page.relative_to(root)
        for number, target in links(page):
            if SCHEME.match(target):
                continue
            file_part, _, anchor = target.partition("#")
            destination = (page.parent / file_part).resolve() if file_part else page
            if not destination.exists():
                problems.append(f"{name}:{number}: link to {target}: no such file or directory")
                continue
            if root not in destination.parents and destination != root:
                problems.append(f"{name}:{number}: link to {target}: outside the repository")
                continue
            if anchor and destination.suffix == ".md" and destination.is_file():
                if anchor not in file_anchors(destination):
                    problems.append(f"{name}:{number}: link to {target}: {destination.relative_to(root)} has no heading "
                                    f"with the anchor #{anchor}")
    return problems


def main():
    root = pathlib.Path(sys.argv[1]) if len(sys.argv) > 1 else pathlib.Path(__file__).resolve().parent.parent
    problems = check(root)
    for problem in problems:
        print(problem)
    if problems:
        print(f"check_docs: {len(problems)} problem(s)")
        return 1
    pages = 1 + len(list((root / "docs").glob("*.md")))
    print(f"check_docs: README.md and {pages - 1} docs/*.md pages: every relative link resolves")
    return 0


if __name__ == "__main__":
    sys.exit(main())
