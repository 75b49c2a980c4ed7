"""The package's import order (cmtool/__init__.py): each layer imports only from the layers below it, lazy
imports inside functions included."""

import ast
from pathlib import Path

import cmtool

ROOT = Path(cmtool.__file__).parent


def layer_of(module: str) -> int:
    """The index in ``cmtool.LAYERS`` of a dotted module name ``cmtool.X...``."""
    part = module.split(".")[1]
    assert part in cmtool.LAYERS, f"{module}: its package {part!r} is in no layer of cmtool.LAYERS"
    return cmtool.LAYERS.index(part)


def imports(path: Path) -> list[tuple[int, str]]:
    """(line, module) of every ``cmtool`` import in a source file, at any depth."""
    package = ".".join(path.relative_to(ROOT.parent).with_suffix("").parts[:-1])
    found = []
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            found += [(node.lineno, a.name) for a in node.names if a.name.startswith("cmtool.")]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                base = ".".join(package.split(".")[:len(package.split(".")) - node.level + 1] + ([base] if base else []))
            if base == "cmtool":  # from cmtool import x: x is a subpackage or module
                found += [(node.lineno, f"cmtool.{a.name}") for a in node.names if a.name != "__version__"]
            elif base.startswith("cmtool."):
                found.append((node.lineno, base))
    return found


def test_every_package_has_a_layer():
    for path in ROOT.iterdir():
        if path.name.startswith(("_", ".")) or path.name == "weights":
            continue
        layer_of(f"cmtool.{path.stem}")


def test_imports_follow_the_layers():
    wrong = []
    for path in sorted(ROOT.rglob("*.py")):
        rel = path.relative_to(ROOT.parent).with_suffix("")
        if rel.parts[1] in ("__init__", "__main__"):
            continue
        own = layer_of(".".join(rel.parts))
        for line, module in imports(path):
            if layer_of(module) > own:
                wrong.append(f"{path.relative_to(ROOT.parent)}:{line} imports {module}")
    assert not wrong, "imports against cmtool.LAYERS:\n" + "\n".join(wrong)


def test_the_check_sees_lazy_and_relative_imports(tmp_path):
    src = tmp_path / "cmtool" / "data" / "x.py"
    src.parent.mkdir(parents=True)
    src.write_text("def f():\n    from cmtool.cli import main\nfrom ..eval import ablations\nfrom cmtool import pipeline\n")
    global ROOT
    saved, ROOT = ROOT, tmp_path / "cmtool"
    try:
        assert sorted(m for _, m in imports(src)) == ["cmtool.cli", "cmtool.eval", "cmtool.pipeline"]
    finally:
        ROOT = saved
    assert layer_of("cmtool.cli") > layer_of("cmtool.data")


def test_the_readme_layout_lists_the_layers_in_order():
    readme = (ROOT.parent / "README.md").read_text(encoding="utf-8")
    block = readme[readme.index("## Layout"):].split("```")[1]
    listed = [line.split()[0].rstrip("/").removesuffix(".py") for line in block.splitlines()
              if line.startswith("  ") and line[2] != " "]
    assert [name for name in listed if name in cmtool.LAYERS] == list(cmtool.LAYERS)
    on_disk = {p.stem for p in ROOT.iterdir() if not p.name.startswith(("_", "."))}
    assert on_disk == set(listed), "README's layout and cmtool/ differ"
