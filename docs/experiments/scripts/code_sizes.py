"""The size of a checkout's code: its largest modules (lines) and its functions over a length (lines,
from ``def`` to the last line, docstring included), over the package's Python files that git tracks
(tests and these scripts left out). It measured the refactor into layers, before and after:

    python docs/experiments/scripts/code_sizes.py [ROOT] [--over 80] [--top 8] [--json FILE]

ROOT defaults to this checkout; for another commit, make a worktree of it
(``git worktree add --detach /tmp/before COMMIT``) and pass its folder. The folder graph of the same
checkout: ``python tests/test_layers.py ROOT``.
"""

from __future__ import annotations

import argparse
import ast
import json
import subprocess
from pathlib import Path

LEFT_OUT = ("tests/", "docs/")


def python_files(root: Path) -> list[Path]:
    """The tracked .py files of the checkout at ``root``, less tests and docs."""
    listed = subprocess.run(["git", "-C", str(root), "ls-files", "*.py"], capture_output=True, text=True,
                            check=True).stdout.split()
    return [root / name for name in listed if not name.startswith(LEFT_OUT)]


def measure(root: Path, over: int = 80, top: int = 8) -> dict:
    """{"modules": [(lines, path)] largest first (``top`` of them), "functions": count,
    "long_functions": [(lines, "path:name")] over ``over`` lines, longest first}."""
    files = python_files(root)
    modules = sorted(((len(p.read_text().splitlines()), str(p.relative_to(root))) for p in files), reverse=True)
    functions = []
    for path in files:
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                functions.append((node.end_lineno - node.lineno + 1, f"{path.relative_to(root)}:{node.name}"))
    functions.sort(reverse=True)
    return {"modules": modules[:top], "functions": len(functions),
            "long_functions": [f for f in functions if f[0] > over]}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("root", nargs="?", type=Path, default=Path(__file__).resolve().parents[3])
    parser.add_argument("--over", type=int, default=80, help="list the functions longer than this (lines)")
    parser.add_argument("--top", type=int, default=8, help="list this many of the largest modules")
    parser.add_argument("--json", type=Path, help="also write the figures to this JSON file")
    args = parser.parse_args(argv)
    sizes = measure(args.root, args.over, args.top)
    print("largest modules:", ", ".join(f"{n} {p}" for n, p in sizes["modules"]))
    print(f"functions: {sizes['functions']}, over {args.over} lines: {len(sizes['long_functions'])}")
    for n, name in sizes["long_functions"]:
        print(f"  {n} {name}")
    if args.json:
        args.json.write_text(json.dumps(sizes, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
