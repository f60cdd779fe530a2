"""What a run was made from: the input's and the masks' digests, the code's revision, the library versions.

A fit depends on more than its configuration: the same command on another video, another
segmentation or another release of a library gives other numbers. ``result.json`` and
``discover.json`` carry :func:`provenance` so two runs that disagree say whether their inputs did.
"""

from __future__ import annotations

import hashlib
import os
import platform
import subprocess
from importlib import metadata
from pathlib import Path

import numpy as np

__all__ = ["provenance", "file_digest", "masks_digest"]

# environment variables that pick the math kernels (MKL's code path, torch's vector instructions)
# or their threads: the same run under other values rounds differently
NUMERICS_ENV = ("MKL_CBWR", "ATEN_CPU_CAPABILITY", "OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_CORETYPE")
PACKAGES = ("torchfit", "torch", "torchdiffeq", "kornia", "numpy", "scipy", "opencv-python-headless", "trimesh",
            "hydra-core")


def file_digest(path: str | Path) -> str | None:
    """SHA-256 of a file's bytes; of a folder, of its files' names, sizes and bytes in name order
    (not recursive); ``None`` when the path is neither (e.g. masks given in memory)."""
    path = Path(path)
    digest = hashlib.sha256()
    if path.is_file():
        files = [path]
    elif path.is_dir():
        files = sorted(p for p in path.iterdir() if p.is_file())
    else:
        return None
    for f in files:
        if path.is_dir():  # each file's name and size first: no two folders hash the same bytes
            digest.update(f"{f.name}\0{f.stat().st_size}\0".encode())
        with open(f, "rb") as stream:
            for block in iter(lambda: stream.read(1 << 20), b""):
                digest.update(block)
    return digest.hexdigest()


def masks_digest(masks) -> str:
    """SHA-256 of (T, H, W) bool masks (their shape, then the bits packed): equal for equal
    segmentations, whatever produced them."""
    masks = np.ascontiguousarray(np.asarray(masks, bool))
    digest = hashlib.sha256(str(masks.shape).encode())
    digest.update(np.packbits(masks).tobytes())
    return digest.hexdigest()


def _revision() -> str | None:
    """``git describe --always --dirty`` of the checkout torchfit is imported from, or ``None``
    when it is not imported from one (an installed wheel)."""
    root = Path(__file__).resolve().parent.parent
    try:
        top = subprocess.run(["git", "rev-parse", "--show-toplevel"], cwd=root, capture_output=True,
                             text=True, timeout=10)
        if top.returncode != 0 or Path(top.stdout.strip()).resolve() != root:
            return None
        described = subprocess.run(["git", "describe", "--always", "--dirty", "--abbrev=12"], cwd=root,
                                   capture_output=True, text=True, timeout=10)
    except (OSError, subprocess.SubprocessError):
        return None
    if described.returncode != 0:
        return None
    return described.stdout.strip() or None


def _version(package: str) -> str | None:
    try:
        return metadata.version(package)
    except metadata.PackageNotFoundError:
        return None


def provenance(source: str | Path | None = None, masks=None) -> dict:
    """What a run was made from, for its output file.

    Args:
        source: the input path (a video file or a folder of images or masks), or ``None``.
        masks: (T, H, W) bool the masks the fit used, or ``None``.

    Returns:
        ``{"source": str | None, "source_sha256": str | None, "masks_sha256": str | None,
        "revision": str | None, "python": str, "packages": {name: version | None},
        "machine": {"cpu": str, "torch_cpu_capability": str, "torch_threads": int,
        "numerics_env": {name: value | None}}}``: the processor, the vector instructions torch's
        kernels use, its threads and the environment variables that choose its math kernels
        (:data:`NUMERICS_ENV`), because the same inputs and libraries on another processor or
        with other kernels round differently and an ill-conditioned fit can end elsewhere.
    """
    return {
        "source": None if source is None else str(source),
        "source_sha256": None if source is None else file_digest(source),
        "masks_sha256": None if masks is None else masks_digest(masks),
        "revision": _revision(),
        "python": platform.python_version(),
        "packages": {name: _version(name) for name in PACKAGES},
        "machine": _machine(),
    }


def _machine() -> dict:
    import torch

    return {"cpu": _cpu_name(), "torch_cpu_capability": torch.backends.cpu.get_cpu_capability(),
            "torch_threads": torch.get_num_threads(),
            "numerics_env": {name: os.environ.get(name) for name in NUMERICS_ENV}}


def _cpu_name() -> str:
    """The processor's model name (Linux's /proc/cpuinfo), else what :mod:`platform` says."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()
