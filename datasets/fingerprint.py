"""A dataset's content hash: the resume key's part that says which scenes a run saw (with the
code's, ``spherebench.provenance.code_version``)."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

from spherebench.datasets import inout
from spherebench.errors import SphereBenchError
from spherebench.provenance import hash_files


def dataset_fingerprint(data_dir: str | Path) -> str:
    """Content hash of a dataset: every file under scenes/ and the ground truth (not its folder name)."""
    root = Path(data_dir)
    scenes = root / "scenes"
    if not scenes.is_dir():
        raise SphereBenchError(f"{root}: not a dataset (no scenes/ folder); build one with 'spherebench generate' "
                               "or 'spherebench prepare'")
    files = sorted(p for p in scenes.rglob("*") if p.is_file() and not any(s.startswith(".") for s in p.parts[-2:]))
    h = hashlib.blake2b(digest_size=16)
    h.update(hash_files(files, root).encode())
    gt = root / "coco_gt.json"
    if gt.is_file():
        coco = inout.read_json(gt)  # a truncated file: one line, not a traceback
        h.update(json.dumps({k: coco.get(k) for k in ("images", "annotations", "categories")},
                            sort_keys=True).encode())
    return h.hexdigest()
