"""Make the committed pictures of README.md and docs/ from today's code, as docs/pictures.toml says.

    python docs/make_pictures.py NAME [NAME ...]   # or: all
    python docs/make_pictures.py --check           # which pictures are older than the code of their commands
    python docs/make_pictures.py --list            # the pictures, their files and commands

For each picture the script empties ``out/pictures/NAME/``, runs the entry's ``commands`` from the repository root,
copies ``output`` to ``picture`` with the commands written into the PNG (tEXt chunks ``Comment``, ``Software``
and ``cmtool digest``) and records in the manifest the ``digest``: sha256 of the commands and of the contents of
the entry's ``sources`` (files, or folders taken whole; ``__pycache__`` and hidden files left out). A picture is
up to date while that digest, the manifest's and the one in the PNG agree (tests/test_pictures.py).

``--compose OUT ROWS GRID:COLUMN ...`` lays panels of ``--grid`` pictures (of ``cmtool sample`` and ``cmtool
baseline``) side by side: for each row index of ROWS (comma separated), the panel in column COLUMN of each GRID.
"""

from __future__ import annotations

import argparse
import hashlib
import re
import shutil
import struct
import subprocess
import sys
import time
import zlib
from pathlib import Path

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    import tomli as tomllib

ROOT = Path(__file__).resolve().parents[1]
MANIFEST = ROOT / "docs" / "pictures.toml"
WORK = "out/pictures"  # each picture's intermediate files: WORK/NAME/
DIGEST_KEY, COMMENT_KEY, SOFTWARE_KEY = "cmtool digest", "Comment", "Software"
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"

# --- the manifest -------------------------------------------------------------------------------------------------


def load_manifest(path: Path = MANIFEST) -> dict[str, dict]:
    """The manifest's pictures by name."""
    return tomllib.loads(path.read_text(encoding="utf-8"))


def remake_command(name: str) -> str:
    return f"python docs/make_pictures.py {name}"


def source_files(sources: list[str], root: Path = ROOT) -> list[Path]:
    """The files of ``sources`` (paths relative to ``root``; a folder gives all its files), sorted by path."""
    files = set()
    for source in sources:
        path = root / source
        if path.is_file():
            files.add(path)
        elif path.is_dir():
            for f in path.rglob("*"):
                rel = f.relative_to(root).parts
                if f.is_file() and "__pycache__" not in rel and not any(p.startswith(".") for p in rel) \
                        and f.suffix != ".pyc":
                    files.add(f)
        else:
            raise FileNotFoundError(f"source {source} does not exist")
    return sorted(files, key=lambda f: f.relative_to(root).as_posix())


def digest(entry: dict, root: Path = ROOT) -> str:
    """sha256 of the entry's commands and of its sources' paths and contents."""
    h = hashlib.sha256()
    for command in entry["commands"]:
        h.update(b"command\0" + command.encode("utf-8") + b"\0")
    for f in source_files(entry["sources"], root):
        data = f.read_bytes()
        h.update(f.relative_to(root).as_posix().encode("utf-8") + b"\0" + str(len(data)).encode() + b"\0" + data)
    return h.hexdigest()


def record_digest(name: str, value: str, path: Path = MANIFEST) -> None:
    """Write ``digest = "value"`` into the manifest's table ``[name]``, keeping everything else as it is."""
    text = path.read_text(encoding="utf-8")
    head = re.search(rf"^\[{re.escape(name)}\][ \t]*$", text, re.M)
    if head is None:
        raise KeyError(f"no [{name}] in {path}")
    nxt = re.search(r"^\[", text[head.end():], re.M)
    end = head.end() + (nxt.start() if nxt else len(text) - head.end())
    table = text[head.end():end]
    line = f'digest = "{value}"'
    if re.search(r"^digest\s*=.*$", table, re.M):
        table = re.sub(r"^digest\s*=.*$", line, table, count=1, flags=re.M)
    else:
        body = table.rstrip("\n")
        table = body + "\n" + line + (table[len(body):] or "\n")
    path.write_text(text[:head.end()] + table + text[end:], encoding="utf-8")


# --- text chunks in a PNG -----------------------------------------------------------------------------------------


def png_chunks(data: bytes) -> list[tuple[bytes, bytes]]:
    """A PNG's chunks as (type, data)."""
    if not data.startswith(PNG_SIGNATURE):
        raise ValueError("not a PNG")
    chunks, pos = [], len(PNG_SIGNATURE)
    while pos < len(data):
        (length,), kind = struct.unpack(">I", data[pos:pos + 4]), data[pos + 4:pos + 8]
        chunks.append((kind, data[pos + 8:pos + 8 + length]))
        pos += 12 + length
    return chunks


def png_text(data: bytes) -> dict[str, str]:
    """A PNG's tEXt chunks as {keyword: text}."""
    out = {}
    for kind, body in png_chunks(data):
        if kind == b"tEXt":
            key, _, value = body.partition(b"\0")
            out[key.decode("latin-1")] = value.decode("latin-1")
    return out


def with_png_text(data: bytes, texts: dict[str, str]) -> bytes:
    """The PNG with tEXt chunks ``texts`` (replacing any of the same keywords), put before the image data."""
    def chunk(kind: bytes, body: bytes) -> bytes:
        return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body) & 0xFFFFFFFF)

    keys = {k.encode("latin-1") for k in texts}
    out, added = [PNG_SIGNATURE], False
    for kind, body in png_chunks(data):
        if kind == b"tEXt" and body.partition(b"\0")[0] in keys:
            continue
        if kind == b"IDAT" and not added:
            out += [chunk(b"tEXt", k.encode("latin-1") + b"\0" + v.encode("latin-1")) for k, v in texts.items()]
            added = True
        out.append(chunk(kind, body))
    return b"".join(out)


def picture_texts(name: str, entry: dict, value: str) -> dict[str, str]:
    commands = "\n".join(f"  {c}" for c in entry["commands"])
    return {COMMENT_KEY: f"{entry['picture']}: made by `{remake_command(name)}` from the repository root, "
                         f"which ran:\n{commands}",
            SOFTWARE_KEY: "cmtool, docs/make_pictures.py", DIGEST_KEY: value}


# --- checking -----------------------------------------------------------------------------------------------------


def stale(name: str, entry: dict, root: Path = ROOT) -> str | None:
    """Why the picture is older than the code of its command, or None when it is up to date."""
    remake = f"remake it with `{remake_command(name)}`"
    picture = root / entry["picture"]
    if not picture.exists():
        return f"{entry['picture']} is missing: {remake}"
    try:
        now = digest(entry, root)
    except FileNotFoundError as e:
        return f"{entry['picture']}: {e}; fix its sources in docs/pictures.toml"
    carried = png_text(picture.read_bytes()).get(DIGEST_KEY)
    if carried is None:
        return f"{entry['picture']} was not made by docs/make_pictures.py (it carries no digest): {remake}"
    if entry.get("digest") != now or carried != now:
        return (f"{entry['picture']} is older than the code of its command (its sources or commands changed "
                f"since it was made): {remake}")
    return None


MACHINE_PATH = re.compile(r"(?<![\w.~/-])(/(?:root|home|work|tmp|Users|mnt|media|opt|var|private|srv|scratch)"
                          r"(?:/|\b)|[A-Za-z]:\\|~/|~[a-z_][\w-]*/)")


def machine_paths(text: str, extra: tuple[str, ...] = ()) -> list[str]:
    """The machine-specific paths in ``text``: absolute paths into home or work folders (/root, /home, /work,
    /tmp, C:\\ ...), ~/..., and any of ``extra`` (this checkout's absolute path, the home folder, the user name as
    a path component)."""
    found = [m.group(0) for m in MACHINE_PATH.finditer(text)]
    found += [e for e in extra if e and e in text]
    return found


# --- making -------------------------------------------------------------------------------------------------------


def make(name: str, entry: dict) -> float:
    """Run the picture's commands, put the picture in place with its text chunks and record its digest; seconds."""
    began = time.perf_counter()
    before = digest(entry)
    work = ROOT / WORK / name
    if work.exists():
        shutil.rmtree(work)
    work.mkdir(parents=True)
    for command in entry["commands"]:
        print(f"[{name}] $ {command}", flush=True)
        t = time.perf_counter()
        done = subprocess.run(command, shell=True, cwd=ROOT)
        if done.returncode != 0:
            sys.exit(f"[{name}] failed with exit status {done.returncode}: {command}")
        print(f"[{name}]   {time.perf_counter() - t:.0f} s", flush=True)
    after = digest(entry)
    if after != before:
        sys.exit(f"[{name}] its sources changed while it was made: run it again")
    output = ROOT / entry["output"]
    if not output.exists():
        sys.exit(f"[{name}] the commands did not write {entry['output']}")
    picture = ROOT / entry["picture"]
    picture.write_bytes(with_png_text(output.read_bytes(), picture_texts(name, entry, after)))
    record_digest(name, after)
    seconds = time.perf_counter() - began
    print(f"[{name}] wrote {entry['picture']} in {seconds:.0f} s", flush=True)
    return seconds


def compose(out: Path, rows: list[int], panels: list[str], panel: int = 256, title: int = 22, gap: int = 4) -> None:
    """Panels of ``--grid`` pictures side by side (``panels``: GRID:COLUMN), one row per index of ``rows``."""
    import cv2
    import numpy as np

    grids = {}
    picked = []
    for spec in panels:
        path, _, column = spec.rpartition(":")
        if path not in grids:
            grids[path] = cv2.imread(str(ROOT / path), cv2.IMREAD_COLOR)
            if grids[path] is None:
                sys.exit(f"cannot read {path}")
        picked.append((grids[path], int(column)))
    h, w = title + panel, panel
    lines = []
    for r in rows:
        tiles = []
        for img, c in picked:
            tile = img[r * (h + gap): r * (h + gap) + h, c * (w + gap): c * (w + gap) + w]
            if tile.shape[:2] != (h, w):
                sys.exit(f"no row {r} / column {c} in a grid of {img.shape[1]} x {img.shape[0]}")
            tiles += [tile, np.full((h, gap, 3), 12, np.uint8)]
        lines += [np.concatenate(tiles[:-1], axis=1), np.full((gap, len(picked) * (w + gap) - gap, 3), 12, np.uint8)]
    out.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(out), np.concatenate(lines[:-1], axis=0))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("names", nargs="*", help="pictures of docs/pictures.toml to make, or all")
    parser.add_argument("--check", action="store_true", help="list the pictures older than their commands' code")
    parser.add_argument("--list", action="store_true", help="list the pictures and their commands")
    parser.add_argument("--compose", nargs="+", metavar="ARG", help="OUT ROWS GRID:COLUMN ...: panels side by side")
    args = parser.parse_args(argv)
    if args.compose:
        if len(args.compose) < 3:
            parser.error("--compose takes OUT ROWS GRID:COLUMN ...")
        compose(ROOT / args.compose[0], [int(r) for r in args.compose[1].split(",")], args.compose[2:])
        return 0
    manifest = load_manifest()
    names = list(manifest) if args.names == ["all"] or (not args.names and (args.check or args.list)) else args.names
    unknown = [n for n in names if n not in manifest]
    if unknown:
        parser.error(f"not in docs/pictures.toml: {', '.join(unknown)} (known: {', '.join(manifest)})")
    if args.list:
        for name in names:
            print(f"{name}: {manifest[name]['picture']}")
            for command in manifest[name]["commands"]:
                print(f"  {command}")
        return 0
    if args.check:
        problems = [p for p in (stale(n, manifest[n]) for n in names) if p]
        for p in problems:
            print(p)
        print(f"{len(names) - len(problems)} of {len(names)} pictures up to date")
        return 1 if problems else 0
    if not names:
        parser.error("name pictures to make (or all), or --check / --list")
    times = {name: make(name, load_manifest()[name]) for name in names}
    if len(times) > 1:
        for name, seconds in times.items():
            print(f"{name}: {seconds:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
