"""A small copy of a shared dataset for a machine that cannot take the original (a lent GPU takes 64 MiB a call):
the images reduced by r into ``images_r/`` (and ``masks_r/``), which the loader reads at ``-r r`` in place of
resampling ``images/`` (the nerfstudio / 3DGS convention), and a COLMAP model without its 2D keypoints and tracks
(the loader reads poses and points only).

    python benchmarks/pack_data.py .gpu/data fox:4 maryrose:8 mi_objects/colmap mi_room/colmap

Each argument is a folder under ../shared/data, with ``:r`` to keep only its images reduced by r (area-averaged as the
loader does; JPEG at quality 95, masks as PNG); without it the folder is copied as it is, keypoints stripped. A run on
the copy at ``-r r`` sees the loader's own reduction of each image up to JPEG's rounding.
"""

from __future__ import annotations

import argparse
import shutil
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
DATA = (ROOT / ".." / "shared" / "data").resolve()


def _write(img: np.ndarray, path: Path) -> None:
    import mitsuba as mi
    u8 = np.clip(np.round(img * 255.0), 0, 255).astype(np.uint8)
    bmp = mi.Bitmap(u8 if u8.ndim == 3 else u8[..., None], mi.Bitmap.PixelFormat.RGB if u8.ndim == 3
                    else mi.Bitmap.PixelFormat.Y)
    bmp.write(str(path), quality=95) if path.suffix.lower() in (".jpg", ".jpeg") else bmp.write(str(path))


def _reduce_folder(src: Path, dst: Path, r: int, mask: bool) -> int:
    from mi_gaussians.data.images import read_image, resize_area
    dst.mkdir(parents=True, exist_ok=True)
    n = 0
    for f in sorted(src.iterdir()):
        if not f.is_file():
            continue
        rgb = read_image(f)[..., :3]
        raw = rgb.mean(axis=2, keepdims=True, dtype=np.float32) if mask else rgb
        h, w = raw.shape[:2]
        small = resize_area(raw, int(round(w / r)), int(round(h / r)))
        _write(small if not mask else small[..., 0], dst / f.name)
        n += 1
    return n


def _strip_model(src: Path, dst: Path) -> None:
    """The COLMAP model in ``src`` as text in ``dst``, without keypoints (images.txt) and tracks (points3D.txt)."""
    import pycolmap
    dst.mkdir(parents=True, exist_ok=True)
    pycolmap.Reconstruction(str(src)).write_text(str(dst))
    lines = (dst / "images.txt").read_text().splitlines()
    out, data = [], 0
    for line in lines:
        if line.startswith("#"):
            out.append(line)
            continue
        out.append(line if data % 2 == 0 else "")
        data += 1
    (dst / "images.txt").write_text("\n".join(out) + "\n")
    pts = [" ".join(line.split()[:8]) if not line.startswith("#") else line
           for line in (dst / "points3D.txt").read_text().splitlines()]
    (dst / "points3D.txt").write_text("\n".join(pts) + "\n")
    for extra in ("frames.txt", "rigs.txt"):
        (dst / extra).unlink(missing_ok=True)


def pack(name: str, dest: Path) -> None:
    folder, _, r = name.partition(":")
    src, out = DATA / folder, dest / folder
    if not src.is_dir():
        raise SystemExit(f"pack_data.py: {src} is not a folder")
    if out.exists():
        shutil.rmtree(out)
    out.mkdir(parents=True)
    for f in src.iterdir():
        if f.is_file():
            shutil.copy2(f, out / f.name)
    sparse = src / "sparse"
    if sparse.is_dir():
        models = [d for d in sorted(sparse.iterdir()) if d.is_dir()] or [sparse]
        for m in models:
            _strip_model(m, out / m.relative_to(src))
    if r:
        r = int(r)
        n = _reduce_folder(src / "images", out / f"images_{r}", r, mask=False)
        if (src / "masks").is_dir():
            _reduce_folder(src / "masks", out / f"masks_{r}", r, mask=True)
        print(f"{folder}: {n} images reduced by {r}", file=sys.stderr)
    else:
        shutil.copytree(src / "images", out / "images")
        print(f"{folder}: copied", file=sys.stderr)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dest", type=Path)
    ap.add_argument("datasets", nargs="+", help="FOLDER or FOLDER:R (under ../shared/data)")
    args = ap.parse_args(argv)
    import mitsuba as mi
    mi.set_variant("scalar_rgb")
    for name in args.datasets:
        pack(name, args.dest.resolve())
    return 0


if __name__ == "__main__":
    sys.exit(main())
