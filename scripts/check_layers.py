#!/usr/bin/env python3
"""Checks that the layers point down (DESIGN.md section 4, STYLE.md rule 13).

core/ includes only core/; host/, kernels/ and weights_io/ include only core/ and their own
folder; the public headers in include/pillarseg/ include only each other and system headers.
engine/, tests/, bench/ and examples/ may include anything below them. Inside engine/, the
sub-folders (backend/, model/, cpu/, ...) form layers too: their includes of each other have no
cycle, and each folder includes only the folders docs/architecture.md's table of engine's
sub-folders lists for it (its "includes" column: folders of the rows above its own, or "anything
above"), so that the documented order is the code's. Prints every include that breaks a rule
(file:line: what), every cycle (the folders, then each include that makes one of its steps) and
every departure from the table, and exits 1 if there is one. A tree without
docs/architecture.md (the tests' small trees) is checked for cycles alone.

Usage: check_layers.py [SOURCE_DIR]   (default: the directory above this script)
"""
import collections
import pathlib
import re
import sys

ALLOWED = {
    "core": {"core"},
    "host": {"core", "host"},
    "kernels": {"core", "kernels"},
    "weights_io": {"core", "weights_io"},
    "include": {"pillarseg"},
}
SUFFIXES = {".hpp", ".cpp", ".h", ".cu", ".cuh"}
QUOTED = re.compile(r'^\s*#\s*include\s+"([^"]+)"')


def violations(root):
    for layer, allowed in ALLOWED.items():
        folder = root / layer
        if not folder.is_dir():
            continue
        for path in sorted(folder.rglob("*")):
            if path.suffix not in SUFFIXES or not path.is_file():
                continue
            for number, line in enumerate(path.read_text(errors="replace").splitlines(), 1):
                match = QUOTED.match(line)
                if not match:
                    continue
                target = match.group(1)
                top = target.split("/", 1)[0] if "/" in target else None
                if top not in allowed:
                    rel = path.relative_to(root)
                    yield f"{rel}:{number}: {layer}/ includes \"{target}\" (allowed: " + \
                          ", ".join(sorted(a + "/" for a in allowed)) + ")"


def engine_includes(root):
    """{(folder, included folder): ["file:line: \"target\"", ...]} between engine/'s sub-folders."""
    edges = collections.defaultdict(list)
    engine = root / "engine"
    if not engine.is_dir():
        return edges
    for path in sorted(engine.rglob("*")):
        if path.suffix not in SUFFIXES or not path.is_file():
            continue
        parts = path.relative_to(engine).parts
        if len(parts) < 2:
            continue
        for number, line in enumerate(path.read_text(errors="replace").splitlines(), 1):
            match = QUOTED.match(line)
            if not match:
                continue
            target = match.group(1).split("/")
            if len(target) < 3 or target[0] != "engine" or target[1] == parts[0]:
                continue
            edges[(parts[0], target[1])].append(f"{path.relative_to(root)}:{number}: \"{match.group(1)}\"")
    return edges


def strongly_connected(nodes, successors):
    """Tarjan's components of the graph, each a sorted list (the graph is a few dozen folders)."""
    index, low, on_stack, stack, found = {}, {}, set(), [], []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in successors[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            found.append(sorted(component))

    for v in sorted(nodes):
        if v not in index:
            visit(v)
    return found


def shortest_cycle(start, members, successors):
    """The shortest path start -> ... -> start through `members` (breadth first)."""
    previous = {}
    queue = collections.deque([start])
    while queue:
        v = queue.popleft()
        for w in successors[v]:
            if w not in members:
                continue
            if w == start:
                path = [v]
                while path[-1] != start:
                    path.append(previous[path[-1]])
                return list(reversed(path)) + [start]
            if w not in previous:
                previous[w] = v
                queue.append(w)
    return [start]


def engine_cycles(root):
    """One message per cycle of includes between engine/'s sub-folders, with the includes of each
    step: in each strongly connected set of folders, the shortest cycle through each folder (the
    same cycle reached from two of its folders once)."""
    edges = engine_includes(root)
    successors = collections.defaultdict(list)
    for source, target in sorted(edges):
        successors[source].append(target)
    nodes = {folder for edge in edges for folder in edge}
    seen = set()
    for component in strongly_connected(nodes, successors):
        if len(component) < 2:
            continue
        for start in component:
            cycle = shortest_cycle(start, set(component), successors)
            steps = frozenset(zip(cycle, cycle[1:]))
            if steps in seen:
                continue
            seen.add(steps)
            lines = ["engine/ sub-folders include each other in a cycle: " +
                     " -> ".join(folder + "/" for folder in cycle)]
            for source, target in zip(cycle, cycle[1:]):
                lines += ["  " + include for include in edges[(source, target)]]
            yield "\n".join(lines)


TABLE_HEADER = re.compile(r"^\|\s*folder\s*\|\s*what\s*\|\s*includes \(in `engine/`\)\s*\|\s*$")
ROW = re.compile(r"^\|\s*`([a-z_]+)/`\s*\|.*\|\s*([^|]*?)\s*\|\s*$")
ANYTHING = "anything above"


def documented_order(root):
    """The table of engine's sub-folders in docs/architecture.md, bottom up: [(folder, the set of
    folders it may include, or ANYTHING)]; None where the tree has no docs/architecture.md. A file
    without the table raises ValueError."""
    doc = root / "docs" / "architecture.md"
    if not doc.is_file():
        return None
    lines = doc.read_text(errors="replace").splitlines()
    start = next((i for i, line in enumerate(lines) if TABLE_HEADER.match(line)), None)
    if start is None:
        raise ValueError("docs/architecture.md: no table of engine's sub-folders (a header "
                         "'| folder | what | includes (in `engine/`) |')")
    rows = []
    for line in lines[start + 2:]:
        match = ROW.match(line)
        if not match:
            break
        folder, includes = match.group(1), match.group(2)
        if includes == ANYTHING:
            rows.append((folder, ANYTHING))
        else:
            rows.append((folder, set(re.findall(r"`([a-z_]+)/`", includes))))
    return rows


def order_departures(root):
    """Each include between engine's sub-folders the table does not allow, and each row of the
    table that lists a folder not above it."""
    rows = documented_order(root)
    if rows is None:
        return
    position = {folder: i for i, (folder, _) in enumerate(rows)}
    for i, (folder, allowed) in enumerate(rows):
        if allowed == ANYTHING:
            continue
        for other in sorted(allowed):
            if position.get(other, len(rows)) >= i:
                yield (f"docs/architecture.md: engine/{folder}/ lists {other}/, which is not a row above "
                       f"its own in the table of engine's sub-folders")
    edges = engine_includes(root)
    folders = sorted({source for source, _ in edges} | {target for _, target in edges} |
                     {p.name for p in (root / "engine").iterdir() if p.is_dir()})
    for folder in folders:
        if folder not in position:
            yield (f"engine/{folder}/ is not in docs/architecture.md's table of engine's sub-folders "
                   f"(add its row where it belongs, with the folders it includes)")
    for (source, target), includes in sorted(edges.items()):
        if source not in position or target not in position:
            continue
        allowed = rows[position[source]][1]
        ok = position[target] < position[source] if allowed == ANYTHING else target in allowed
        if not ok:
            lines = [f"engine/{source}/ includes engine/{target}/, which docs/architecture.md's table "
                     f"does not allow it (it lists: " +
                     (ANYTHING if allowed == ANYTHING else ", ".join(sorted(a + "/" for a in allowed)) or "-") +
                     ")"]
            lines += ["  " + include for include in includes]
            yield "\n".join(lines)


def main():
    root = pathlib.Path(sys.argv[1] if len(sys.argv) > 1 else pathlib.Path(__file__).parent.parent)
    found = list(violations(root.resolve()))
    cycles = list(engine_cycles(root.resolve()))
    try:
        departures = list(order_departures(root.resolve()))
    except ValueError as e:
        departures = [str(e)]
    for v in found + cycles + departures:
        print(v)
    if found:
        print(f"check_layers: {len(found)} include(s) point up or sideways")
    if cycles:
        print(f"check_layers: {len(cycles)} cycle(s) of includes between engine/'s sub-folders")
    if departures:
        print(f"check_layers: {len(departures)} departure(s) from docs/architecture.md's order of engine's "
              "sub-folders")
    if found or cycles or departures:
        return 1
    ordered = "" if documented_order(root.resolve()) is None else \
        ", in docs/architecture.md's order"
    print("check_layers: every layer includes only the layers below it, and engine/'s sub-folders "
          f"include each other without a cycle{ordered}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
