"""Fetch a public real capture for the benchmarks, with its provenance: one folder of images
from a public git repository at a pinned commit, every file checked against its pinned sha256,
written to OUT/NAME/images with OUT/NAME/PROVENANCE.json beside it.

    python benchmarks/data/fetch_capture.py aloe                    # clones from GitHub
    python benchmarks/data/fetch_capture.py aloe --source GIT_DIR   # from a local clone or mirror

The images are never committed to this repository; experiment files read them by path
(experiments/auto_real.toml). A capture has no poses: `ghsplat sfm` makes them.
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import hashlib
import shutil
import subprocess
import sys
import tarfile
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # benchmarks/
from record import ROOT  # noqa: E402

DEFAULT_OUT = ROOT / "runs" / "real_captures"


@dataclasses.dataclass(frozen=True)
class Capture:
    """A folder of photos in a public repository, pinned to a commit and to each file's hash.

    Args:
        repo: GitHub owner/name.
        commit: the full commit hash the files are read at.
        folder: the folder inside the repository that holds the photos.
        sha256: {file name: sha256} of every photo, so a fetch either gives these bytes or fails.
        what: what the photos show and how they were taken.
        licence: the terms the repository states (or that it states none).
        cite: whom to credit.
    """

    repo: str
    commit: str
    folder: str
    sha256: dict[str, str]
    what: str
    licence: str
    cite: str


CAPTURES = {
    "aloe": Capture(
        repo="Deb0r0h/3D-Structure-from-motion",
        commit="b8e8da2e65742c38ee451d6e446a1cba686b7fa9",
        folder="datasets/images_2",
        sha256={
            "00.jpg": "a79ae057a63d61e314930cba91d90a0677f5232468426377ad4def65bdb15cd9",
            "01.jpg": "0f5823b3a60829c03ff812aa0f44418b8595fca3b3c3d3ff7547075e06f85c36",
            "02.jpg": "543bafb1df19e9365075e39a7b3dfba669c59955786b48054b88f94c83c85b8b",
            "03.jpg": "7fe78ac3813781f133acfb5828dbab64cf9017e0a8b0902ec75db09c2bc306e5",
            "04.jpg": "9bf19816801ae5f5191ddea614352ebdac9c2c81dbdaf6202259d2f0ca0c4677",
            "05.jpg": "5ec4390f2f43c38fe25e52a1ffd20b5a233a1caa33777de8aa21ef14b257e641",
            "06.jpg": "252e495ba7638347de29ecc05531956e5f60229e60e2598deaf38c346c84c668",
            "07.jpg": "534022b8bdde4a000bfab6ff9b2b54347b8f2ae40cedd2dc1a85e66bb304af9f",
            "08.jpg": "03f28f0a00d15af6a068e8a3dde149f7174f67c99e864ea2fd5b5e00a54db274",
            "09.jpg": "623bee862b8c0f5d3f6ae2b88029cf8662c2bcdfbd088efc00c40a9594424e95",
            "10.jpg": "f8be2bcccffad235c9e358bc9548861983a35a3affcaefd2427869944e0ef737",
            "11.jpg": "8619f359d773356d0521ffcbc1abbc448a76e7f8302841bd7a3d857193064bc4",
            "12.jpg": "52aa21b569d90b346c0e4e8a265f09d4c3d597e5909a4689fba14e69c9641274",
            "14.jpg": "5760236ee19f877ed2de11c91672bfaa560545cc66d7748b98cb32e993972ea6",
            "15.jpg": "940f528b09a41f148f6d2da9de04b2b3390a43e3597b5b69a5282071902b3a45",
        },
        what="15 smartphone photos (Samsung SM-A750FN, 2022, resized to 1133x850 JPG) of a potted aloe "
             "in a wicker basket on a table against a wall, taken from the front half of the plant",
        licence="the repository states no licence; used here for research benchmarking only, never redistributed",
        cite="the repository's authors (owner Deb0r0h; the commit by Gabriel Taormina), "
             "https://github.com/Deb0r0h/3D-Structure-from-motion",
    ),
}


def _export(source: str, capture: Capture, into: Path) -> Path:
    """The capture's folder at its commit, extracted under `into` (a local git dir or a clone)."""
    if not Path(source).exists():  # a URL: a shallow fetch of the one commit
        clone = into / "clone"
        subprocess.run(["git", "init", "-q", str(clone)], check=True)
        subprocess.run(["git", "-C", str(clone), "fetch", "-q", "--depth", "1", source, capture.commit], check=True)
        source = str(clone / ".git")
    archive = into / "folder.tar"
    with archive.open("wb") as fh:
        subprocess.run(["git", "--git-dir", source, "archive", capture.commit, capture.folder], stdout=fh, check=True)
    with tarfile.open(archive) as tar:
        tar.extractall(into / "tree", filter="data")
    return into / "tree" / capture.folder


def _sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def fetch(name: str, out: Path, source: str | None = None) -> Path:
    """Write capture `name` to OUT/NAME/images and OUT/NAME/PROVENANCE.json; return OUT/NAME.
    Raises SystemExit naming the file when a photo is missing or its bytes differ from the pin.
    The folder appears whole or not at all (made beside it, then renamed)."""
    from ghsplat_jax.io_utils import code_revision, write_json

    capture = CAPTURES[name]
    source = source or f"https://github.com/{capture.repo}.git"
    target = out / name
    out.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=out, prefix=f".{name}-") as scratch:
        folder = _export(source, capture, Path(scratch))
        staged = Path(scratch) / name
        (staged / "images").mkdir(parents=True)
        for file, expected in sorted(capture.sha256.items()):
            path = folder / file
            if not path.is_file():
                raise SystemExit(f"{source}: {capture.folder}/{file} is missing at {capture.commit}")
            if (got := _sha256(path)) != expected:
                raise SystemExit(f"{source}: {capture.folder}/{file} has sha256 {got}, pinned {expected}")
            shutil.copy2(path, staged / "images" / file)
        write_json(staged / "PROVENANCE.json", {
            "capture": name, "source": f"https://github.com/{capture.repo}", "fetched_from": source,
            "commit": capture.commit, "folder": capture.folder, "files": capture.sha256, "what": capture.what,
            "licence": capture.licence, "cite": capture.cite,
            "fetched_at": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
            "fetched_by": f"benchmarks/data/fetch_capture.py at {code_revision()}"})
        shutil.rmtree(target, ignore_errors=True)
        staged.rename(target)
    return target


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("name", choices=sorted(CAPTURES))
    ap.add_argument("--source", help="a local git dir or clone URL holding the commit (default: its GitHub URL)")
    ap.add_argument("--out", type=Path, default=DEFAULT_OUT)
    args = ap.parse_args(argv)
    target = fetch(args.name, args.out, args.source)
    print(f"wrote {target}/images ({len(CAPTURES[args.name].sha256)} photos) and {target}/PROVENANCE.json")
    return 0


if __name__ == "__main__":
    sys.exit(main())
