"""Lines per module and the largest functions and classes of a source tree (``ast``-based),
for an architecture note's before/after table::

    python -m epc_offboard.tools.code_size [ROOT] [--top N] [--under PREFIX ...]

``ROOT`` is a checkout (default: this one) or its package folder; lines are physical lines
of each file, a function's or class's lines run from its first decorator to its last line.
``--under`` keeps only modules whose dotted name starts with one of the prefixes (e.g.
``fleet control.epc``). Read-only: it parses, never imports, what it measures.
"""

from __future__ import annotations

import argparse
import ast
from dataclasses import dataclass
from pathlib import Path

_PACKAGE = "epc_offboard"


@dataclass(frozen=True)
class Definition:
    qualname: str  # module:Class.method
    kind: str  # "function" or "class"
    lines: int


def package_dir(root: Path) -> Path:
    """The package folder under ``root`` (or ``root`` itself when it is the package)."""
    return root / _PACKAGE if (root / _PACKAGE).is_dir() else root


def module_name(pkg: Path, path: Path) -> str:
    parts = path.relative_to(pkg).with_suffix("").parts
    return ".".join(p for p in parts if p != "__init__") or "__init__"


def definitions(module: str, source: str) -> list[Definition]:
    """Every function and class of ``source``, nested ones included, with its length."""
    out: list[Definition] = []

    def walk(node: ast.AST, prefix: str) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.FunctionDef | ast.AsyncFunctionDef | ast.ClassDef):
                first = min([child.lineno] + [d.lineno for d in child.decorator_list])
                name = f"{prefix}{child.name}"
                kind = "class" if isinstance(child, ast.ClassDef) else "function"
                out.append(Definition(f"{module}:{name}", kind,
                                      (child.end_lineno or child.lineno) - first + 1))  # fmt: skip
                walk(child, name + ".")
            else:
                walk(child, prefix)

    walk(ast.parse(source), "")
    return out


def measure(
    root: Path, under: tuple[str, ...] = ()
) -> tuple[dict[str, int], list[Definition]]:
    """(lines by module, every definition) of the package under ``root``."""
    pkg = package_dir(root)
    sizes: dict[str, int] = {}
    defs: list[Definition] = []
    for path in sorted(pkg.rglob("*.py")):
        name = module_name(pkg, path)
        if under and not any(name == u or name.startswith(u + ".") for u in under):
            continue
        source = path.read_text(encoding="utf-8")
        sizes[name] = len(source.splitlines())
        defs += definitions(name, source)
    return sizes, defs


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("root", nargs="?", type=Path, default=Path(__file__).parents[2])
    ap.add_argument("--top", type=int, default=15, help="largest functions and classes shown")
    ap.add_argument("--under", nargs="*", default=[], help="dotted module prefixes kept")
    args = ap.parse_args(argv)
    sizes, defs = measure(args.root, tuple(args.under))
    print(f"{'lines':>6}  module   ({len(sizes)} modules, {sum(sizes.values())} lines)")
    for name, n in sorted(sizes.items(), key=lambda kv: (-kv[1], kv[0])):
        print(f"{n:>6}  {name}")
    for kind in ("class", "function"):
        print(f"\n{'lines':>6}  largest {kind}{'es' if kind == 'class' else 's'}")
        ranked = sorted((d for d in defs if d.kind == kind), key=lambda d: (-d.lines, d.qualname))
        for d in ranked[: args.top]:
            print(f"{d.lines:>6}  {d.qualname}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
