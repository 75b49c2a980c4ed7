"""The committed pictures of README.md and docs/ are made by docs/make_pictures.py from today's code: each is listed
in docs/pictures.toml, carries the digest of its commands and of the code they run (a picture older than that code
fails, naming the command that remakes it), and neither its commands, the text it carries nor the docs' captions
hold a path of one machine."""

import getpass
import importlib.util
import re
import shutil
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
IMAGE = re.compile(r"!\[([^\]]*)\]\(([^)\s]+\.png)\)|<img [^>]*src=\"([^\"]+\.png)\"")


def _load_script():
    spec = importlib.util.spec_from_file_location("make_pictures", ROOT / "docs" / "make_pictures.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


mp = _load_script()
MANIFEST = mp.load_manifest()


def _extra_machine_strings() -> tuple[str, ...]:
    """This checkout's absolute path, the home folder and the user name as a path component."""
    extra = [str(ROOT), str(Path.home())]
    try:
        user = getpass.getuser()
        extra += [f"/{user}/", f"\\{user}\\"]
    except Exception:  # no user name to be had
        pass
    return tuple(e for e in extra if e not in ("/", ""))


def referenced_pictures() -> dict[str, list[str]]:
    """Each picture shown by README.md or docs/*.md (repository-relative path) -> the pages showing it."""
    found: dict[str, list[str]] = {}
    for page in PAGES:
        for m in IMAGE.finditer(page.read_text(encoding="utf-8")):
            target = m.group(2) or m.group(3)
            if re.match(r"[a-z]+:", target):
                continue  # a picture on the web
            path = (page.parent / target).resolve().relative_to(ROOT).as_posix()
            found.setdefault(path, []).append(page.relative_to(ROOT).as_posix())
    return found


def captions(page: Path) -> list[tuple[str, str]]:
    """(picture, text) for each picture of the page: the image line and the blocks (paragraph or fenced code)
    just before and after it, where the docs say what the picture shows and how it was made."""
    blocks, current, fenced = [], [], False
    for line in page.read_text(encoding="utf-8").splitlines():
        if line.strip().startswith("```"):
            current.append(line)
            fenced = not fenced
            if not fenced:
                blocks.append("\n".join(current))
                current = []
            continue
        if not fenced and not line.strip():
            if current:
                blocks.append("\n".join(current))
            current = []
        else:
            current.append(line)
    if current:
        blocks.append("\n".join(current))
    out = []
    for k, block in enumerate(blocks):
        for m in IMAGE.finditer(block):
            around = blocks[max(k - 1, 0): k + 2]
            out.append((m.group(2) or m.group(3), "\n".join(around)))
    return out


def test_every_shown_picture_is_in_the_manifest():
    listed = {entry["picture"] for entry in MANIFEST.values()}
    missing = {p: pages for p, pages in referenced_pictures().items() if p not in listed}
    assert not missing, ("pictures shown in the docs but not in docs/pictures.toml (add how each is made): "
                         + "; ".join(f"{p} (in {', '.join(pages)})" for p, pages in missing.items()))


def test_manifest_entries_are_complete():
    for name, entry in MANIFEST.items():
        for key in ("picture", "output", "commands", "sources"):
            assert entry.get(key), f"docs/pictures.toml [{name}] has no {key}"
        assert entry["output"].startswith(f"{mp.WORK}/{name}/"), \
            f"[{name}]: its output must lie in {mp.WORK}/{name}/, which the script empties before each run"
        assert entry["picture"].endswith(".png") and (ROOT / entry["picture"]).parent.is_dir()


@pytest.mark.parametrize("name", list(MANIFEST))
def test_picture_is_made_from_todays_code(name):
    problem = mp.stale(name, MANIFEST[name])
    assert problem is None, problem


@pytest.mark.parametrize("name", list(MANIFEST))
def test_no_machine_paths_in_commands_or_picture(name):
    entry, extra = MANIFEST[name], _extra_machine_strings()
    for text in [*entry["commands"], entry["output"], *entry["sources"]]:
        assert not mp.machine_paths(text, extra), f"[{name}] of docs/pictures.toml holds a machine path: {text}"
    picture = ROOT / entry["picture"]
    if picture.exists():
        for key, text in mp.png_text(picture.read_bytes()).items():
            found = mp.machine_paths(text, extra)
            assert not found, f"{entry['picture']}'s text chunk {key!r} holds a machine path: {found}"


@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.relative_to(ROOT).as_posix())
def test_no_machine_paths_in_picture_captions(page):
    extra = _extra_machine_strings()
    bad = [(picture, mp.machine_paths(text, extra)) for picture, text in captions(page)]
    bad = [(picture, found) for picture, found in bad if found]
    assert not bad, f"{page.name}: the words around these pictures hold machine paths: {bad}"


def test_machine_paths_found():
    extra = ("/srv/checkout",)
    for text in ["cmtool sample --out /root/x", "see /home/ana/maps", "C:\\Users\\ana\\x.png", "~/runs/a",
                 "python /work/main/docs/make_pictures.py", "/tmp/x.png", "cd /srv/checkout && make"]:
        assert mp.machine_paths(text, extra), text
    for text in ["cmtool sample --osm ../shared/data/osm/x.osm.pbf --out out/pictures/a", "docs/viewer_area.png",
                 "out/tmp/x.png", "SD | generated | ground truth", "ratio 3/4 of roads"]:
        assert not mp.machine_paths(text, extra), text


def test_a_picture_older_than_its_code_fails(tmp_path):
    """A picture made by the script is up to date; changing a source, a command or the picture's carried digest
    makes it stale, and the message names the command that remakes it."""
    (tmp_path / "docs").mkdir()
    (tmp_path / "pkg" / "sub" / "__pycache__").mkdir(parents=True)
    (tmp_path / "pkg" / "draw.py").write_text("COLOUR = 1\n")
    (tmp_path / "pkg" / "sub" / "w.json").write_text("{}")
    (tmp_path / "pkg" / "sub" / "__pycache__" / "draw.cpython-311.pyc").write_bytes(b"x")
    shutil.copy(ROOT / "sample_data" / "sd_bos.png", tmp_path / "made.png")  # a picture a command made
    manifest = tmp_path / "docs" / "pictures.toml"
    manifest.write_text('# pictures\n\n[demo]\npicture = "docs/demo.png"\noutput = "out/pictures/demo/demo.png"\n'
                        'commands = ["cmtool data show x --png out/pictures/demo/demo.png"]\n'
                        'sources = ["pkg"]\n\n[other]\npicture = "docs/other.png"\n')
    entry = mp.load_manifest(manifest)["demo"]
    value = mp.digest(entry, tmp_path)
    mp.record_digest("demo", value, manifest)
    entry = mp.load_manifest(manifest)["demo"]
    assert entry["digest"] == value and mp.load_manifest(manifest)["other"] == {"picture": "docs/other.png"}
    png = mp.with_png_text((tmp_path / "made.png").read_bytes(), mp.picture_texts("demo", entry, value))
    (tmp_path / "docs" / "demo.png").write_bytes(png)
    assert mp.png_text(png)[mp.DIGEST_KEY] == value and "cmtool data show" in mp.png_text(png)[mp.COMMENT_KEY]
    import cv2
    import numpy as np
    decoded = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
    assert (decoded == cv2.imread(str(tmp_path / "made.png"), cv2.IMREAD_COLOR)).all()  # the pixels as they were
    assert mp.stale("demo", entry, tmp_path) is None

    (tmp_path / "pkg" / "sub" / "__pycache__" / "draw.cpython-311.pyc").write_bytes(b"y")  # not a source
    assert mp.stale("demo", entry, tmp_path) is None

    (tmp_path / "pkg" / "draw.py").write_text("COLOUR = 2\n")  # the code that draws it changed
    problem = mp.stale("demo", entry, tmp_path)
    assert problem and "docs/demo.png" in problem and "python docs/make_pictures.py demo" in problem
    (tmp_path / "pkg" / "draw.py").write_text("COLOUR = 1\n")
    assert mp.stale("demo", entry, tmp_path) is None

    changed = dict(entry, commands=["cmtool data show x --n 4 --png out/pictures/demo/demo.png"])
    assert "python docs/make_pictures.py demo" in mp.stale("demo", changed, tmp_path)

    (tmp_path / "docs" / "demo.png").write_bytes((tmp_path / "made.png").read_bytes())  # a picture made by hand
    assert "python docs/make_pictures.py demo" in mp.stale("demo", entry, tmp_path)
