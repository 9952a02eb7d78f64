"""numpy <-> sensor_msgs/PointCloud2, vectorised (one structured array, no per-point loops).

The stack's clouds are unorganised (height 1) float32 clouds with the fields
``x y z [normal_x normal_y normal_z] [extra float32 fields...] [rgb]``. ``rgb`` is the packed
float32 RViz expects (the bytes of the uint32 0x00RRGGBB). Reading accepts any layout a
driver may send (organised clouds, padding, float64 or big-endian fields) and rejects
malformed ones with a :class:`CloudFormatError` that says what is wrong.
"""

from __future__ import annotations

import array
from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np
from sensor_msgs.msg import PointCloud2, PointField
from std_msgs.msg import Header

XYZ = ("x", "y", "z")
NORMALS = ("normal_x", "normal_y", "normal_z")

_NP_OF_POINTFIELD = {
    PointField.INT8: np.int8,
    PointField.UINT8: np.uint8,
    PointField.INT16: np.int16,
    PointField.UINT16: np.uint16,
    PointField.INT32: np.int32,
    PointField.UINT32: np.uint32,
    PointField.FLOAT32: np.float32,
    PointField.FLOAT64: np.float64,
}
_POINTFIELD_OF_NP = {np.dtype(v).str[1:]: k for k, v in _NP_OF_POINTFIELD.items()}


class CloudFormatError(ValueError):
    """A PointCloud2 that cannot be read as the stack needs it (and why)."""


@dataclass
class CloudArrays:
    """The arrays of one cloud: points, optional normals, other per-point fields."""

    points: np.ndarray  # (N, 3) float32
    normals: np.ndarray | None = None  # (N, 3) float32
    fields: dict[str, np.ndarray] = field(default_factory=dict)  # name -> (N,)
    frame_id: str = ""

    def __len__(self) -> int:
        return len(self.points)


# --- colours -------------------------------------------------------------------------------

def pack_rgb(rgb: np.ndarray) -> np.ndarray:
    """(N, 3) colours (uint8 0-255 or float 0-1) -> (N,) float32 holding 0x00RRGGBB bits."""
    rgb = np.asarray(rgb)
    if rgb.ndim != 2 or rgb.shape[1] != 3:
        raise ValueError(f"colours must be (N, 3), got {rgb.shape}")
    if rgb.dtype.kind == "f":
        rgb = np.clip(np.rint(rgb * 255.0), 0, 255)
    c = rgb.astype(np.uint32)
    packed = (c[:, 0] << 16) | (c[:, 1] << 8) | c[:, 2]
    return packed.view(np.float32)


def unpack_rgb(packed: np.ndarray) -> np.ndarray:
    """(N,) packed float32 ``rgb`` -> (N, 3) uint8."""
    c = np.ascontiguousarray(packed, dtype=np.float32).view(np.uint32)
    return np.stack([(c >> 16) & 0xFF, (c >> 8) & 0xFF, c & 0xFF], axis=1).astype(np.uint8)


# blue -> cyan -> green -> yellow -> red: low affordance cold, high hot
_HEAT_STOPS = np.array(
    [[0, 0, 255], [0, 255, 255], [0, 255, 0], [255, 255, 0], [255, 0, 0]], dtype=np.float64
)


def heatmap_rgb(values: np.ndarray, vmin: float = 0.0, vmax: float = 1.0) -> np.ndarray:
    """(N,) scalars -> (N, 3) uint8 heat colours; NaNs are grey."""
    v = np.asarray(values, dtype=np.float64)
    t = np.clip((v - vmin) / max(vmax - vmin, 1e-12), 0.0, 1.0)
    t = np.nan_to_num(t, nan=0.0)
    pos = t * (len(_HEAT_STOPS) - 1)
    lo = np.minimum(pos.astype(np.int64), len(_HEAT_STOPS) - 2)
    w = (pos - lo)[:, None]
    rgb = _HEAT_STOPS[lo] * (1.0 - w) + _HEAT_STOPS[lo + 1] * w
    rgb[np.isnan(v)] = 128.0
    return np.rint(rgb).astype(np.uint8)


# --- writing -------------------------------------------------------------------------------

def arrays_to_cloud(
    points: np.ndarray,
    normals: np.ndarray | None = None,
    fields: Mapping[str, np.ndarray] | None = None,
    rgb: np.ndarray | None = None,
    frame_id: str = "world",
    stamp=None,
    header: Header | None = None,
) -> PointCloud2:
    """Build an unorganised PointCloud2 from (N, 3) points and optional per-point arrays.

    ``fields`` values keep their dtype when it has a PointField type (float32 otherwise
    becomes float32: bool -> uint8, int64 -> int32); ``rgb`` is (N, 3) colours, packed.
    """
    pts = np.asarray(points, dtype=np.float32)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"points must be (N, 3), got {pts.shape}")
    n = len(pts)
    columns: list[tuple[str, np.ndarray]] = [(name, pts[:, i]) for i, name in enumerate(XYZ)]
    if normals is not None:
        nrm = np.asarray(normals, dtype=np.float32)
        if nrm.shape != pts.shape:
            raise ValueError(f"normals {nrm.shape} do not match points {pts.shape}")
        columns += [(name, nrm[:, i]) for i, name in enumerate(NORMALS)]
    for name, values in (fields or {}).items():
        v = np.asarray(values)
        if v.shape != (n,):
            raise ValueError(f"field {name!r} must be ({n},), got {v.shape}")
        if v.dtype == bool:
            v = v.astype(np.uint8)
        elif v.dtype == np.int64:
            v = v.astype(np.int32)
        elif v.dtype == np.uint64:
            v = v.astype(np.uint32)
        elif v.dtype.str[1:] not in _POINTFIELD_OF_NP:
            v = v.astype(np.float32)
        columns.append((name, v))
    if rgb is not None:
        columns.append(("rgb", pack_rgb(rgb)))
    names = [c[0] for c in columns]
    if len(set(names)) != len(names):
        raise ValueError(f"duplicate field names in {names}")

    # little-endian packed layout, each field at its natural offset in declaration order
    dtype = np.dtype([(name, v.dtype.newbyteorder("<")) for name, v in columns])
    rec = np.empty(n, dtype=dtype)
    for name, v in columns:
        rec[name] = v

    msg = PointCloud2()
    if header is not None:
        msg.header = header
    else:
        msg.header.frame_id = frame_id
        if stamp is not None:
            msg.header.stamp = stamp
    msg.height = 1
    msg.width = n
    msg.fields = [
        PointField(
            name=name,
            offset=dtype.fields[name][1],
            datatype=_POINTFIELD_OF_NP[dtype.fields[name][0].str[1:]],
            count=1,
        )
        for name in names
    ]
    msg.is_bigendian = False
    msg.point_step = dtype.itemsize
    msg.row_step = dtype.itemsize * n
    msg.is_dense = bool(np.isfinite(pts).all())
    data = array.array("B")
    data.frombytes(rec.tobytes())
    msg.data = data
    return msg


# --- reading -------------------------------------------------------------------------------

def cloud_dtype(msg: PointCloud2) -> np.dtype:
    """The numpy structured dtype of one point of ``msg`` (checked against point_step)."""
    if msg.point_step <= 0:
        raise CloudFormatError(f"point_step is {msg.point_step}")
    names, formats, offsets = [], [], []
    for f in msg.fields:
        if f.datatype not in _NP_OF_POINTFIELD:
            raise CloudFormatError(f"field {f.name!r} has unknown datatype {f.datatype}")
        base = np.dtype(_NP_OF_POINTFIELD[f.datatype]).newbyteorder(
            ">" if msg.is_bigendian else "<")
        count = max(int(f.count), 1)
        fmt = base if count == 1 else np.dtype((base, (count,)))
        if f.offset + fmt.itemsize > msg.point_step:
            raise CloudFormatError(
                f"field {f.name!r} (offset {f.offset}, {fmt.itemsize} bytes) does not fit in "
                f"point_step {msg.point_step}")
        if f.name in names:
            raise CloudFormatError(f"field {f.name!r} appears twice")
        names.append(f.name)
        formats.append(fmt)
        offsets.append(f.offset)
    spans = sorted((o, o + fmt.itemsize, n) for o, fmt, n in zip(offsets, formats, names,
                                                                 strict=True))
    for (_, end, a), (start, _, b) in zip(spans, spans[1:], strict=False):
        if start < end:
            raise CloudFormatError(f"fields {a!r} and {b!r} overlap (offsets in point_step "
                                   f"{msg.point_step})")
    return np.dtype(
        {"names": names, "formats": formats, "offsets": offsets, "itemsize": msg.point_step})


def cloud_to_structured(msg: PointCloud2) -> np.ndarray:
    """All points of ``msg`` as one (height * width,) structured array (a view, no copy)."""
    dtype = cloud_dtype(msg)
    h, w = int(msg.height), int(msg.width)
    if h * w == 0:
        return np.empty(0, dtype=dtype)
    row_step = int(msg.row_step) if msg.row_step else w * msg.point_step
    if row_step < w * msg.point_step:
        raise CloudFormatError(f"row_step {row_step} < width {w} x point_step {msg.point_step}")
    buf = np.frombuffer(msg.data, dtype=np.uint8)
    need = row_step * (h - 1) + w * msg.point_step
    if not need <= buf.size <= row_step * h:
        raise CloudFormatError(
            f"data has {buf.size} bytes; {h} rows of {w} points of row_step {row_step} "
            f"need {need}" + ("" if need == row_step * h else f" to {row_step * h}"))
    # rows may be padded: a strided view handles both layouts, reshape copies only if padded
    grid = np.ndarray((h, w), dtype=dtype, buffer=buf, strides=(row_step, msg.point_step))
    return grid.reshape(-1)


MOVABLE_FIELD = "movable"
"""Per-point 0/1 field of the simulator's clouds: the point lies on a movable part (ground
truth, as the reference proposes exploration and manipulation on movable parts in
simulation). A real camera's cloud has no such field; every node works without it."""


def movable_mask(msg: PointCloud2) -> np.ndarray | None:
    """(N,) bool from the cloud's ``movable`` field, None when it has none or none is set."""
    if not any(f.name == MOVABLE_FIELD for f in msg.fields):
        return None
    mask = cloud_to_arrays(msg, fields=(MOVABLE_FIELD,)).fields[MOVABLE_FIELD] > 0
    return mask if mask.any() else None


def cloud_to_arrays(
    msg: PointCloud2,
    require_normals: bool = False,
    fields: tuple[str, ...] | None = None,
    drop_nonfinite: bool = False,
) -> CloudArrays:
    """Read points (+ normals when present, + the named or all other fields) as float arrays.

    ``drop_nonfinite`` removes points whose coordinates (or normals) are NaN/inf, as the
    invalid pixels of a depth camera's organised cloud are; otherwise they are kept.
    """
    rec = cloud_to_structured(msg)
    names = rec.dtype.names or ()
    missing = [c for c in XYZ if c not in names]
    if missing:
        raise CloudFormatError(f"cloud has no {'/'.join(missing)} field(s); fields: {list(names)}")
    has_normals = all(c in names for c in NORMALS)
    if require_normals and not has_normals:
        raise CloudFormatError(f"cloud needs normal_x/normal_y/normal_z; fields: {list(names)}")
    points = np.stack([rec[c].astype(np.float32) for c in XYZ], axis=1)
    normals = (np.stack([rec[c].astype(np.float32) for c in NORMALS], axis=1)
               if has_normals else None)
    skip = set(XYZ) | set(NORMALS)
    wanted = fields if fields is not None else tuple(n for n in names if n not in skip)
    extra: dict[str, np.ndarray] = {}
    for name in wanted:
        if name not in names:
            raise CloudFormatError(f"cloud has no field {name!r}; fields: {list(names)}")
        v = rec[name]
        extra[name] = v.astype(v.dtype.newbyteorder("="))  # native byte order, owned copy
    if drop_nonfinite:
        ok = np.isfinite(points).all(axis=1)
        if normals is not None:
            ok &= np.isfinite(normals).all(axis=1)
        if not ok.all():
            points = points[ok]
            normals = normals[ok] if normals is not None else None
            extra = {k: v[ok] for k, v in extra.items()}
    return CloudArrays(points=points, normals=normals, fields=extra, frame_id=msg.header.frame_id)
