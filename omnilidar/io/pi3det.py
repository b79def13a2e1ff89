"""Pi3DET-style info pickles: one dict per frame, a list per pickle.

Each info holds ``frame_id``, ``platform`` (Vehicle, Drone or Quadruped),
``point_clout_path`` (sic: Pi3DET's own spelling, kept so that its tools read
our files), a path relative to the dataset root of a float32 x, y, z,
intensity ``.bin``, and ``annos`` {``gt_names`` (M,) str, ``gt_boxes_lidar``
(M, 7) x, y, z_center, dx, dy, dz, heading}. Names are Car and Pedestrian;
Pi3DET's "Vehicle" is an alias of Car and is stored as Car. Extra keys (e.g.
Pi3DET's ``calib``) are kept as they are.

Pickle risk: unpickling can run arbitrary code named by the file. Info files
are untrusted input, so :func:`read_infos` uses a restricted unpickler that
can only rebuild plain Python containers and scalars and numpy arrays,
dtypes and scalars; any other global (``os.system``, ``builtins.eval``, a
class from some package) is refused before it is called. It cannot stop a
hostile file from asking for a lot of memory; read pickles from sources you
trust. After loading, every info is validated (keys, types, shapes, names).
"""

from __future__ import annotations

import pickle
from collections.abc import Iterable
from pathlib import Path, PurePosixPath, PureWindowsPath

import numpy as np

from omnilidar.errors import InputError
from omnilidar.io import pointfile, semantickitti
from omnilidar.io.atomic import write_bytes_atomic
from omnilidar.lidar.scan import Boxes, Scan

CLASSES: tuple[str, ...] = ("Car", "Pedestrian")
CLASS_ALIASES: dict[str, str] = {"Vehicle": "Car"}
PLATFORMS: tuple[str, ...] = ("Vehicle", "Drone", "Quadruped")
# Classes annotated per platform (the drone data labels cars only).
PLATFORM_CLASSES: dict[str, tuple[str, ...]] = {
    "Vehicle": CLASSES, "Drone": ("Car",), "Quadruped": CLASSES,
}
POINT_PATH_KEY = "point_clout_path"  # sic
REQUIRED_KEYS: tuple[str, ...] = ("frame_id", "platform", POINT_PATH_KEY)

# Globals a pickle of plain dicts/lists and numpy arrays needs (numpy 1.x and
# 2.x module names, pickle protocols 2-5). Nothing here can run user code.
_SAFE_GLOBALS: frozenset[tuple[str, str]] = frozenset({
    ("numpy", "ndarray"),
    ("numpy", "dtype"),
    ("numpy.core.multiarray", "_reconstruct"),
    ("numpy._core.multiarray", "_reconstruct"),
    ("numpy.core.multiarray", "scalar"),
    ("numpy._core.multiarray", "scalar"),
    ("numpy.core.numeric", "_frombuffer"),
    ("numpy._core.numeric", "_frombuffer"),
    ("_codecs", "encode"),  # protocol-2 pickles store array bytes as latin-1 text
    ("collections", "OrderedDict"),
})


class _RestrictedUnpickler(pickle.Unpickler):
    def find_class(self, module: str, name: str):
        if (module, name) not in _SAFE_GLOBALS:
            raise pickle.UnpicklingError(f"refusing to load {module}.{name} (not a plain data type)")
        return super().find_class(module, name)


def canonical_name(name: str) -> str:
    """Map a Pi3DET class name to ours ("Vehicle" -> "Car")."""
    return CLASS_ALIASES.get(name, name)


def _check_relative(where, path: str) -> None:
    if not isinstance(path, str) or not path:
        raise InputError(where, f"{POINT_PATH_KEY} must be a non-empty string, got {path!r}")
    for flavour in (PurePosixPath, PureWindowsPath):
        p = flavour(path)
        if p.is_absolute() or p.drive or ".." in p.parts:
            raise InputError(where, f"{POINT_PATH_KEY} must be relative to the dataset root, got {path!r}")


def _check_annos(where, annos) -> dict:
    if not isinstance(annos, dict):
        raise InputError(where, f"annos must be a dict, got {type(annos).__name__}")
    for key in ("gt_names", "gt_boxes_lidar"):
        if key not in annos:
            raise InputError(where, f"annos lacks {key!r}")
    names = np.asarray(annos["gt_names"])
    if names.ndim != 1 or not all(isinstance(n, str) for n in names.tolist()):
        raise InputError(where, "annos.gt_names must be a 1-D sequence of strings")
    names = np.array([canonical_name(n) for n in names.tolist()], dtype=str).reshape(-1)
    unknown = sorted(set(names.tolist()) - set(CLASSES))
    if unknown:
        raise InputError(where, f"unknown class names {unknown}; known: {', '.join(CLASSES)} (alias Vehicle)")
    boxes = np.asarray(annos["gt_boxes_lidar"])
    if boxes.dtype.kind not in "fiu":
        raise InputError(where, f"annos.gt_boxes_lidar must be numeric, got dtype {boxes.dtype}")
    if boxes.size == 0:
        boxes = boxes.reshape(0, 7)
    if boxes.ndim != 2 or boxes.shape[1] != 7:
        raise InputError(where, f"annos.gt_boxes_lidar must be (M, 7), got {boxes.shape}")
    if len(boxes) != len(names):
        raise InputError(where, f"{len(boxes)} boxes but {len(names)} names")
    boxes = boxes.astype(np.float32)
    if not np.isfinite(boxes).all():
        raise InputError(where, "annos.gt_boxes_lidar holds NaN or infinite values")
    if (boxes[:, 3:6] <= 0).any():
        raise InputError(where, "annos.gt_boxes_lidar has non-positive box sizes")
    return {**annos, "gt_names": names, "gt_boxes_lidar": boxes}


def _validate_info(where, info) -> dict:
    """Check one info dict; return a normalised copy (names canonical, boxes float32)."""
    if not isinstance(info, dict):
        raise InputError(where, f"must be a dict, got {type(info).__name__}")
    for key in REQUIRED_KEYS:
        if key not in info:
            raise InputError(where, f"lacks {key!r}")
    frame_id = info["frame_id"]
    if isinstance(frame_id, bool) or not isinstance(frame_id, (str, int, np.integer)):
        raise InputError(where, f"frame_id must be a string or int, got {type(frame_id).__name__}")
    if info["platform"] not in PLATFORMS:
        raise InputError(where, f"unknown platform {info['platform']!r}; known: {', '.join(PLATFORMS)}")
    _check_relative(where, info[POINT_PATH_KEY])
    out = dict(info)
    if "annos" in info:
        out["annos"] = _check_annos(where, info["annos"])
    return out


def make_info(frame_id: str, platform: str, point_path: str, boxes: Boxes) -> dict:
    """Build one Pi3DET info dict (validated; "Vehicle" boxes become "Car")."""
    info = {
        "frame_id": frame_id,
        "platform": platform,
        POINT_PATH_KEY: str(PurePosixPath(point_path)) if isinstance(point_path, Path) else point_path,
        "annos": {"gt_names": np.asarray(boxes.names), "gt_boxes_lidar": np.asarray(boxes.boxes)},
    }
    return _validate_info(f"info {frame_id!r}", info)


def write_infos(path: str | Path, infos: Iterable[dict]) -> None:
    """Validate ``infos`` and pickle them as a list, atomically."""
    checked = [_validate_info(f"{path}: info[{i}]", info) for i, info in enumerate(infos)]
    write_bytes_atomic(path, pickle.dumps(checked, protocol=4))


def read_infos(path: str | Path) -> list[dict]:
    """Load an info pickle with the restricted unpickler and validate each info."""
    path = pointfile.require_file(path)
    try:
        with open(path, "rb") as fh:
            data = _RestrictedUnpickler(fh).load()
    except pickle.UnpicklingError as err:
        raise InputError(path, f"unsafe or corrupt pickle: {err}") from None
    except (EOFError, ValueError, TypeError, AttributeError, ImportError, IndexError, KeyError,
            MemoryError, UnicodeDecodeError) as err:
        raise InputError(path, f"not a valid pickle ({type(err).__name__}: {err})") from None
    if not isinstance(data, (list, tuple)):
        raise InputError(path, f"must hold a list of info dicts, got {type(data).__name__}")
    return [_validate_info(f"{path}: info[{i}]", info) for i, info in enumerate(data)]


def read_scan(info: dict, root: str | Path, intensity_scale: float = 1.0) -> Scan:
    """Read the scan an info points to (relative to ``root``), with its boxes.

    Points are float32 x, y, z, intensity; intensity must lie in
    0..``intensity_scale``. Empty scans are an error.
    """
    where = f"info {info.get('frame_id')!r}" if isinstance(info, dict) else "info"
    info = _validate_info(where, info)
    root = pointfile.require_dir(root, "Pi3DET root")
    bin_path = root / info[POINT_PATH_KEY]
    points = semantickitti.read_points(bin_path)
    if len(points) == 0:
        raise InputError(bin_path, "scan has 0 points (an empty sweep means a truncated or failed export)")
    pointfile.check_range(
        bin_path, points[:, 3], 0.0, intensity_scale, "intensity",
        hint=f"; pass the dataset's intensity_scale (now {intensity_scale:g})",
    )
    boxes = Boxes.empty()
    if "annos" in info:
        boxes = Boxes(info["annos"]["gt_boxes_lidar"], info["annos"]["gt_names"])
    return Scan(points=points, boxes=boxes, intensity_scale=float(intensity_scale))
