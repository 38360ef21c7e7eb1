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
        self._manifest_written = False

    # -- frames -------------------------------------------------------------------------------
    def write_frame(self, frame: int, samples: dict) -> None:
        if self._chunk is None:
            self._chunk = Sdf.Layer.CreateAnonymous(".usdc")
            self._chunk_first = frame
        layer = self._chunk
        for (prim_path, name, type_name), value in samples.items():
            prim = layer.GetPrimAtPath(prim_path) or Sdf.CreatePrimInLayer(layer, prim_path)
            prim.specifier = Sdf.SpecifierOver
            attr_path = Sdf.Path(prim_path).AppendProperty(name)
            if layer.GetAttributeAtPath(attr_path) is None:
                Sdf.AttributeSpec(prim, name, _VALUE_TYPES[type_name][0])
            conv = _VALUE_TYPES[type_name][1]
            layer.SetTimeSample(attr_path, float(frame), conv(value) if conv else value)
            self._attrs[(prim_path, name)] = type_name
        self._last_frame = frame
        if frame - self._chunk_first + 1 >= self.chunk_size(len(self.chunks)):
            self.flush()

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
        m = Sdf.Layer.CreateAnonymous(".usdc")
        for (prim_path, name), type_name in self._attrs.items():
            prim = m.GetPrimAtPath(prim_path) or Sdf.CreatePrimInLayer(m, prim_path)
            prim.specifier = Sdf.SpecifierOver
            Sdf.AttributeSpec(prim, name, _VALUE_TYPES[type_name][0])
        _atomic_export(m, self.clip_dir / f"manifest{self.ext}")

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
