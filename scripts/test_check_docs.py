#!/usr/bin/env python3
"""Tests of check_docs.py on small trees: a clean one passes; a README over 250 lines, a link to a
missing file and a link to a missing heading each fail and are named by file and line; links in
code, external links and repeated headings' anchors are handled as on GitHub."""
import pathlib
import subprocess
import sys
import tempfile
import unittest

SCRIPT = pathlib.Path(__file__).with_name("check_docs.py")


def run(files):
    with tempfile.TemporaryDirectory() as d:
        root = pathlib.Path(d)
        for name, text in files.items():
            path = root / name
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_text(text)
        done = subprocess.run([sys.executable, str(SCRIPT), str(root)], capture_output=True, text=True)
        return done.returncode, done.stdout


CLEAN = {
    "README.md": "# tool\n\nSee [the design](docs/design.md#the-op-graph) and [bench](bench/README.md),\n"
                 "[a folder](examples/), [the site](https://example.org/x) and [mail](mailto:a@b.c).\n"
                 "[ref]: docs/design.md\n",
    "docs/design.md": "# Design\n\n## The op graph\n\n## `pillarseg render`: panels (0.1 m)\n\n## Notes\n\n## Notes\n\n"
                      "Back to the [README](../README.md#tool), [here](#the-op-graph), "
                      "[code](#pillarseg-render-panels-01-m), [second notes](#notes-1).\n"
                      "```sh\ncat [not a link](missing.md)\n```\n"
                      "Inline `[not a link](missing.md)` either.\n",
    "bench/README.md": "# Benchmarks\n",
    "examples/app.c": "int main(void) { return 0; }\n",
}


class CheckDocs(unittest.TestCase):
    def test_clean_tree_passes(self):
        code, out = run(CLEAN)
        self.assertEqual(code, 0, out)
        self.assertIn("every relative link resolves", out)

    def test_long_readme_fails(self):
        files = dict(CLEAN)
        files["README.md"] = CLEAN["README.md"] + "line\n" * 246  # 251 lines
        code, out = run(files)
        self.assertEqual(code, 1)
        self.assertIn("README.md: 251 lines, at most 250", out)
        files["README.md"] = CLEAN["README.md"] + "line\n" * 245  # 250 lines
        self.assertEqual(run(files)[0], 0)

    def test_missing_file_is_named_with_its_line(self):
        files = dict(CLEAN)
        files["docs/other.md"] = "# Other\n\nsee [python](python.md)\n"
        code, out = run(files)
        self.assertEqual(code, 1)
        self.assertIn("docs/other.md:3: link to python.md: no such file or directory", out)

    def test_missing_anchor_fails(self):
        files = dict(CLEAN)
        files["README.md"] = CLEAN["README.md"].replace("#the-op-graph", "#the-graph")
        code, out = run(files)
        self.assertEqual(code, 1)
        self.assertIn("README.md:3: link to docs/design.md#the-graph: docs/design.md has no heading with the "
                      "anchor #the-graph", out)
        files = dict(CLEAN)
        files["docs/design.md"] = CLEAN["docs/design.md"].replace("#notes-1", "#notes-2")
        code, out = run(files)
        self.assertEqual(code, 1)
        self.assertIn("#notes-2", out)

    def test_reference_links_are_checked(self):
        files = dict(CLEAN)
        files["README.md"] = CLEAN["README.md"].replace("[ref]: docs/design.md", "[ref]: docs/gone.md")
        code, out = run(files)
        self.assertEqual(code, 1)
        self.assertIn("README.md:5: link to docs/gone.md", out)


if __name__ == "__main__":
    unittest.main()
