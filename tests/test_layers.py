"""The package's import order (cmtool/__init__.py): each layer imports only from the layers below it, and within
a package no modules import each other in a circle; lazy imports inside functions included."""

import ast
from pathlib import Path

import cmtool

ROOT = Path(cmtool.__file__).parent


def layer_of(module: str) -> int:
    """The index in ``cmtool.LAYERS`` of a dotted module name ``cmtool.X...``."""
    part = module.split(".")[1]
    assert part in cmtool.LAYERS, f"{module}: its package {part!r} is in no layer of cmtool.LAYERS"
    return cmtool.LAYERS.index(part)


def is_module(module: str) -> bool:
    """Whether the dotted name ``cmtool.X...`` is a module or package of the tree under ``ROOT``."""
    path = ROOT.parent.joinpath(*module.split("."))
    return path.with_suffix(".py").is_file() or (path / "__init__.py").is_file()


def imports(path: Path) -> list[tuple[int, str]]:
    """(line, module) of every ``cmtool`` import in a source file, at any depth; ``from P import m`` names the module
    ``P.m`` where that is a module of the tree, else ``P``."""
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
                named = [f"{base}.{a.name}" if is_module(f"{base}.{a.name}") else base for a in node.names]
                found += [(node.lineno, module) for module in dict.fromkeys(named)]
    return found


def module_of(path: Path) -> str:
    """The dotted name of a source file under ``ROOT`` (a package's ``__init__.py``: the package)."""
    parts = path.relative_to(ROOT.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def circles() -> list[list[str]]:
    """The import circles inside one package (the modules of one folder under ``ROOT``, its ``__init__.py``
    included): every strongly connected component of more than one module, each as the imports that tie it
    ("path:line imports module")."""
    files = {module_of(path): path for path in sorted(ROOT.rglob("*.py"))}
    edges = {name: [(line, module) for line, module in imports(path)
                    if module != name and module in files and files[module].parent == path.parent]
             for name, path in files.items()}
    reached = {}
    for name in files:
        seen, todo = set(), [name]
        while todo:
            for _, module in edges[todo.pop()]:
                if module not in seen:
                    seen.add(module)
                    todo.append(module)
        reached[name] = seen
    found = {frozenset(m for m in reached[name] if name in reached[m]) for name in files if name in reached[name]}
    return sorted([f"{files[a].relative_to(ROOT.parent)}:{line} imports {b}" for a in sorted(circle)
                   for line, b in edges[a] if b in circle] for circle in found)


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


def test_no_package_has_an_import_circle():
    found = circles()
    assert not found, "import circles inside a package:\n" + "\n\n".join("\n".join(c) for c in found)


def test_the_check_finds_a_circle_of_lazy_and_relative_imports(tmp_path):
    files = {"__init__.py": "", "sample/__init__.py": "", "sample/a.py": "from cmtool.sample.b import x\n",
             "sample/b.py": "def f():\n    from . import a\n", "sample/c.py": "from cmtool.sample import b\n",
             "core/__init__.py": "", "core/d.py": "from cmtool.sample import a\n",
             "core/e.py": "import cmtool.core.d\n"}
    for name, text in files.items():
        (tmp_path / "cmtool" / name).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / "cmtool" / name).write_text(text)
    global ROOT
    saved, ROOT = ROOT, tmp_path / "cmtool"
    try:
        assert circles() == [["cmtool/sample/a.py:1 imports cmtool.sample.b",
                              "cmtool/sample/b.py:2 imports cmtool.sample.a"]]
        (tmp_path / "cmtool" / "core" / "d.py").write_text("def f():\n    import cmtool.core.e\n")
        assert [c[0] for c in circles()] == ["cmtool/core/d.py:2 imports cmtool.core.e",
                                             "cmtool/sample/a.py:1 imports cmtool.sample.b"]
    finally:
        ROOT = saved


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
