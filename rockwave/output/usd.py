"""USD output: one stage per run, frames written in chunks joined by value clips.

Layout of a run's USD output ``frames.usdc``:
- ``frames.usdc``: the root layer: stage metadata (upAxis, metersPerUnit = 1,
  timeCodesPerSecond = framesPerSecond = frame rate, start/end time codes), the static parts of
  every prim (ids, widths, mesh topology) and the clip set that points at the chunks;
- ``frames.clips/chunk_NNNN.usdc``: the time samples of 1, 2, 4, ... frames, then ``chunk_frames`` each (the
  stage on disk holds the first frame at once);
- ``frames.clips/manifest.usdc``: the clip manifest (which attributes vary in time).
Every file is written to a temporary name and renamed into place, so a killed run leaves the
frames written so far in a stage that opens, and never a torn file.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
from pxr import Sdf, Usd, UsdGeom, Vt


def _atomic_export(layer: Sdf.Layer, path: Path) -> None:
    tmp = path.with_name(f".{path.stem}.tmp{path.suffix}")
    try:
        ok = layer.Export(str(tmp))
    except Exception:  # pxr raises Tf.ErrorException on a full disk or an unwritable folder
        ok = False
    if not ok:
        why = "disk full, file size limit or folder not writable"
        try:
            tmp.unlink()
        except OSError:
            pass
        raise OSError(f"cannot write {path} ({why})")
    os.replace(tmp, path)


_VALUE_TYPES = {
    "point3f[]": (Sdf.ValueTypeNames.Point3fArray, lambda a: Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(a, dtype=np.float32))),
    "vector3f[]": (Sdf.ValueTypeNames.Vector3fArray, lambda a: Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(a, dtype=np.float32))),
    "float[]": (Sdf.ValueTypeNames.FloatArray, lambda a: Vt.FloatArray.FromNumpy(np.ascontiguousarray(a, dtype=np.float32))),
    "float3": (Sdf.ValueTypeNames.Float3, lambda a: tuple(float(c) for c in a)),
    "double3": (Sdf.ValueTypeNames.Double3, lambda a: tuple(float(c) for c in a)),
    "quatf": (Sdf.ValueTypeNames.Quatf, None),
    "int[]": (Sdf.ValueTypeNames.IntArray, lambda a: Vt.IntArray.FromNumpy(np.ascontiguousarray(a, dtype=np.int32))),
    "float3[]": (Sdf.ValueTypeNames.Float3Array, lambda a: Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(a, dtype=np.float32))),
    "normal3f[]": (Sdf.ValueTypeNames.Normal3fArray, lambda a: Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(a, dtype=np.float32))),
    # (n, 4) as (x, y, z, w): Gf.Quatf's memory order (imaginary part, then real)
    "quatf[]": (Sdf.ValueTypeNames.QuatfArray, lambda a: Vt.QuatfArray.FromNumpy(np.ascontiguousarray(a, dtype=np.float32))),
    "quath[]": (Sdf.ValueTypeNames.QuathArray, lambda a: Vt.QuathArray.FromNumpy(np.ascontiguousarray(a, dtype=np.float16))),
}


class UsdFrameWriter:
    """Writes frames into a chunked, clip-joined USD stage.

    ``setup(stage)`` defines the static prims on the root stage. Each frame is a dict
    ``{(prim_path, attr_name, type_name): value}`` of time samples.
    """

    def __init__(self, path: str | os.PathLike, fps: float, up_axis: str, setup, chunk_frames: int = 50):
        self.path = Path(path)
        self.fps = float(fps)
        self.chunk_frames = int(chunk_frames)
        self.clip_dir = self.path.with_name(self.path.stem + ".clips")
        self.clip_dir.mkdir(parents=True, exist_ok=True)
        self.ext = self.path.suffix if self.path.suffix in (".usdc", ".usda") else ".usdc"
        self.stage = Usd.Stage.CreateInMemory()
        UsdGeom.SetStageUpAxis(self.stage, UsdGeom.Tokens.z if up_axis == "Z" else UsdGeom.Tokens.y)
        UsdGeom.SetStageMetersPerUnit(self.stage, 1.0)
        self.stage.SetTimeCodesPerSecond(self.fps)
        self.stage.SetFramesPerSecond(self.fps)
        self.stage.SetStartTimeCode(0)
        self.stage.SetEndTimeCode(0)
        root = UsdGeom.Xform.Define(self.stage, "/World")
        self.stage.SetDefaultPrim(root.GetPrim())
        setup(self.stage)
        self.chunks: list[tuple[int, int]] = []  # (first frame, last frame) per chunk written
        self._chunk: Sdf.Layer | None = None
        self._chunk_first = 0
        self._last_frame = -1
        self._attrs: dict[tuple[str, str], str] = {}
        self._manifest_attrs: dict | None = None  # the attributes the manifest on disk lists (rewritten when they change)

    # -- frames -------------------------------------------------------------------------------
    def write_frame(self, frame: int, samples: dict) -> None:
        if self._chunk is None:
            self._chunk = Sdf.Layer.CreateAnonymous(".usdc")
            self._chunk_first = frame
        layer = self._chunk
        with Sdf.ChangeBlock():  # one change notice for the frame's samples
            self._write_samples(layer, frame, samples)
        self._last_frame = frame
        if frame - self._chunk_first + 1 >= self.chunk_size(len(self.chunks)):
            self.flush()

    def _write_samples(self, layer: Sdf.Layer, frame: int, samples: dict) -> None:
        for (prim_path, name, type_name), value in samples.items():
            prim = layer.GetPrimAtPath(prim_path) or Sdf.CreatePrimInLayer(layer, prim_path)
            prim.specifier = Sdf.SpecifierOver
            attr_path = Sdf.Path(prim_path).AppendProperty(name)
            if layer.GetAttributeAtPath(attr_path) is None:
                Sdf.AttributeSpec(prim, name, _VALUE_TYPES[type_name][0])
            conv = _VALUE_TYPES[type_name][1]
            layer.SetTimeSample(attr_path, float(frame), conv(value) if conv else value)
            self._attrs[(prim_path, name)] = type_name

    def chunk_size(self, index: int) -> int:
        """Frames in chunk ``index``: 1, 2, 4, ... up to chunk_frames, so the stage on disk holds the first
        frame at once and a killed run keeps all but its last few frames (a dozen extra files at most)."""
        return min(self.chunk_frames, 1 << min(index, 30))

    def flush(self) -> None:
        """Write the open chunk and rewrite the root layer so the stage includes it."""
        if self._chunk is None:
            return
        idx = len(self.chunks)
        name = f"chunk_{idx:04d}{self.ext}"
        _atomic_export(self._chunk, self.clip_dir / name)
        self.chunks.append((self._chunk_first, self._last_frame))
        self._chunk = None
        self._write_manifest()
        self._write_root()

    def close(self) -> None:
        self.flush()
        if not self.chunks:
            self._write_root()

    # -- checkpoint and resume (rockwave/sim/checkpoint.py) -----------------------------------------
    def checkpoint_state(self, tag: str) -> dict:
        """What a resumed writer needs; the open (unflushed) chunk is saved as ``open_<tag>`` in the
        clip folder, so chunk boundaries, and the files, are those of an uninterrupted run."""
        open_name = None
        if self._chunk is not None:
            open_name = f"open_{tag}{self.ext}"
            _atomic_export(self._chunk, self.clip_dir / open_name)
        return {"chunks": [list(c) for c in self.chunks], "chunk_first": self._chunk_first, "last_frame": self._last_frame,
                "attrs": [[p, n, t] for (p, n), t in self._attrs.items()], "open_chunk": open_name, "ext": self.ext}

    def restore_checkpoint_state(self, st: dict) -> None:
        """Continue from :meth:`checkpoint_state`: chunk files written after it are dropped and the
        root layer is rewritten, so the stage on disk ends at the checkpoint's frame."""
        if st["ext"] != self.ext:
            raise ValueError(f"the checkpoint's USD files are {st['ext']}, this run writes {self.ext}")
        self.chunks = [tuple(c) for c in st["chunks"]]
        self._attrs = {(p, n): t for p, n, t in st["attrs"]}
        self._chunk_first, self._last_frame = st["chunk_first"], st["last_frame"]
        self._chunk = None
        if st["open_chunk"]:
            src = Sdf.Layer.FindOrOpen(str(self.clip_dir / st["open_chunk"]))
            if src is None:
                raise OSError(f"cannot resume: {self.clip_dir / st['open_chunk']} is missing or unreadable")
            self._chunk = Sdf.Layer.CreateAnonymous(".usdc")
            self._chunk.TransferContent(src)
        for p in self.clip_dir.glob(f"chunk_*{self.ext}"):
            try:
                stale = int(p.stem.split("_")[1]) >= len(self.chunks)
            except (IndexError, ValueError):
                stale = False
            if stale:
                p.unlink()
        if self.chunks:
            self._write_manifest()
        self._write_root()

    # -- layers -------------------------------------------------------------------------------
    def _write_manifest(self) -> None:
        if self._manifest_attrs == self._attrs and (self.clip_dir / f"manifest{self.ext}").is_file():
            return  # unchanged (with many blocks rewriting it at every chunk cost seconds)
        m = Sdf.Layer.CreateAnonymous(".usdc")
        for (prim_path, name), type_name in self._attrs.items():
            prim = m.GetPrimAtPath(prim_path) or Sdf.CreatePrimInLayer(m, prim_path)
            prim.specifier = Sdf.SpecifierOver
            Sdf.AttributeSpec(prim, name, _VALUE_TYPES[type_name][0])
        _atomic_export(m, self.clip_dir / f"manifest{self.ext}")
        self._manifest_attrs = dict(self._attrs)

    def _write_root(self) -> None:
        st = self.stage
        rel = self.clip_dir.name
        if self.chunks:
            clips = Usd.ClipsAPI(st.GetPrimAtPath("/World"))
            clips.SetClipAssetPaths(Sdf.AssetPathArray([f"./{rel}/chunk_{i:04d}{self.ext}" for i in range(len(self.chunks))]))
            clips.SetClipPrimPath("/World")
            clips.SetClipManifestAssetPath(Sdf.AssetPath(f"./{rel}/manifest{self.ext}"))
            clips.SetClipActive(Vt.Vec2dArray([(float(a), float(i)) for i, (a, _) in enumerate(self.chunks)]))
            times = []
            for a, b in self.chunks:  # identity map; a one-frame chunk gets one entry (a repeated time is a jump)
                times += [(float(a), float(a))] + ([(float(b), float(b))] if b != a else [])
            clips.SetClipTimes(Vt.Vec2dArray(times))
            st.SetStartTimeCode(self.chunks[0][0])
            st.SetEndTimeCode(self.chunks[-1][1])
        _atomic_export(st.GetRootLayer(), self.path)


def points_setup(prim_path: str, n: int, width: float, ids: np.ndarray | None = None):
    """Static part of a particle prim: ids and widths (positions and velocities are time-sampled)."""

    def setup(stage):
        pts = UsdGeom.Points.Define(stage, prim_path)
        pts.CreateWidthsAttr(Vt.FloatArray.FromNumpy(np.full(n, width, dtype=np.float32)))
        pts.SetWidthsInterpolation(UsdGeom.Tokens.vertex)
        i = np.arange(n, dtype=np.int64) if ids is None else ids.astype(np.int64)
        pts.CreateIdsAttr(Vt.Int64Array.FromNumpy(i))

    return setup


# ------------------------------------------------------------------------------------------------
# many prims at once: Sdf specs authored straight into a layer
# ------------------------------------------------------------------------------------------------

AUTHOR_BATCH = 5000  # prims per Sdf.ChangeBlock (and between two progress calls)


def _def_prim(layer: Sdf.Layer, path: str, type_name: str) -> Sdf.PrimSpec:
    spec = layer.GetPrimAtPath(path) or Sdf.CreatePrimInLayer(layer, path)
    spec.specifier = Sdf.SpecifierDef
    spec.typeName = type_name
    return spec


def define_meshes(layer: Sdf.Layer, parent: str, meshes, progress=None, parent_type: str = "Scope") -> None:
    """``def Mesh`` prims under ``parent`` (made a ``def <parent_type>``), authored as Sdf specs straight into
    ``layer`` (a stage's root layer) in Sdf.ChangeBlocks of AUTHOR_BATCH prims: what UsdGeom.Mesh.Define and its
    Create*Attr / AddTranslateOp / AddOrientOp author, without the stage recomposing after each prim (which made
    set-up time grow as the square of the block count). Identical geometry shares its converted arrays.

    ``meshes``: a list of (name, key, points, faces, posed): ``key`` names the geometry (equal keys: equal points and
    faces); ``points`` (k, 3) or None (time-sampled elsewhere); ``faces`` lists of vertex indices; ``posed``: a
    ``double3 xformOp:translate`` and ``quatf xformOp:orient`` op, time-sampled elsewhere. ``progress(done, total)``
    is called after each batch."""
    top = _def_prim(layer, parent, parent_type)
    cache: dict = {}
    order = Vt.TokenArray(["xformOp:translate", "xformOp:orient"])
    names = Sdf.ValueTypeNames
    total = len(meshes)
    for lo in range(0, total, AUTHOR_BATCH):
        with Sdf.ChangeBlock():
            for name, key, points, faces, posed in meshes[lo:lo + AUTHOR_BATCH]:
                arrays = cache.get(key)
                if arrays is None:
                    pts = None if points is None else Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(points, dtype=np.float32))
                    arrays = cache[key] = (pts, Vt.IntArray([len(f) for f in faces]), Vt.IntArray([int(i) for f in faces for i in f]))
                pts, counts, indices = arrays
                spec = Sdf.PrimSpec(top, name, Sdf.SpecifierDef, "Mesh")
                Sdf.AttributeSpec(spec, "faceVertexCounts", names.IntArray).default = counts
                Sdf.AttributeSpec(spec, "faceVertexIndices", names.IntArray).default = indices
                if pts is not None:
                    Sdf.AttributeSpec(spec, "points", names.Point3fArray).default = pts
                Sdf.AttributeSpec(spec, "subdivisionScheme", names.Token, Sdf.VariabilityUniform).default = "none"
                if posed:
                    Sdf.AttributeSpec(spec, "xformOp:translate", names.Double3)
                    Sdf.AttributeSpec(spec, "xformOp:orient", names.Quatf)
                    Sdf.AttributeSpec(spec, "xformOpOrder", names.TokenArray, Sdf.VariabilityUniform).default = order
        if progress is not None:
            progress(min(lo + AUTHOR_BATCH, total), total)


def instancer_orientation_attr() -> tuple[str, str]:
    """(attribute, type) of a PointInstancer's orientations: float precision (``orientationsf``, USD >= 24.11) where the
    schema has it, else the half-precision ``orientations``."""
    if "orientationsf" in UsdGeom.PointInstancer.GetSchemaAttributeNames():
        return "orientationsf", "quatf[]"
    return "orientations", "quath[]"


def define_instancer(layer: Sdf.Layer, path: str, prototypes, proto_indices: np.ndarray, ids: np.ndarray) -> None:
    """A ``def PointInstancer`` at ``path`` with its prototypes (``def Mesh`` prims under ``path/prototypes``, in body
    coordinates: a list of (points, faces)), ``protoIndices`` and ``ids``; ``positions`` and the orientations
    (instancer_orientation_attr) are time-sampled per frame."""
    _def_prim(layer, path, "PointInstancer")
    protos = f"{path}/prototypes"
    define_meshes(layer, protos, [(f"p_{k}", k, pts, faces, False) for k, (pts, faces) in enumerate(prototypes)],
                  parent_type="Scope")
    names = Sdf.ValueTypeNames
    with Sdf.ChangeBlock():
        spec = layer.GetPrimAtPath(path)
        rel = Sdf.RelationshipSpec(spec, "prototypes", custom=False)
        for k in range(len(prototypes)):
            rel.targetPathList.explicitItems.append(Sdf.Path(f"{protos}/p_{k}"))
        Sdf.AttributeSpec(spec, "protoIndices", names.IntArray).default = Vt.IntArray.FromNumpy(
            np.ascontiguousarray(proto_indices, dtype=np.int32))
        Sdf.AttributeSpec(spec, "ids", names.Int64Array).default = Vt.Int64Array.FromNumpy(np.ascontiguousarray(ids, dtype=np.int64))
        Sdf.AttributeSpec(spec, "positions", names.Point3fArray)
        name, type_name = instancer_orientation_attr()
        Sdf.AttributeSpec(spec, name, _VALUE_TYPES[type_name][0])
