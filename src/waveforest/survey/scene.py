"""The survey's scene: meshes (PLY, OBJ + MTL), plants as instances of prototypes, ground.

A plant ``(species, x, y, z, height, seed, rotation)`` is a copy of the prototype built by
:func:`waveforest.vegetation.build` (no ground) at the height rounded to ``height_step_m``
and the seed ``seed % prototype_seeds``: a bounded set of prototypes, each built and given
its BVH once (:func:`waveforest.mcrt.prepare_prototypes`), copied by transform only.
"""

from __future__ import annotations

import math
import re
import time
import warnings
from contextlib import suppress
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from waveforest.constants import KIND_GROUND
from waveforest.errors import WaveforestError, WaveforestWarning
from waveforest.mcrt import prepare
from waveforest.scene import Scene, SceneError, fan_triangles, read_ply
from waveforest.survey.spec import SCENE_SCHEMA, SURVEY_SCHEMA, SurveyError, read_document, resolve
from waveforest.vegetation import build, species_params

KINDS = {"ground": 0, "leaf": 1, "wood": 2, "other": 3}


@dataclass(frozen=True)
class Plants:
    """Plant copies: ``prototypes[which[j]]`` rotated by ``rotation[j]`` and moved by ``translation[j]``."""

    prototypes: tuple[Scene, ...]
    labels: tuple[str, ...]
    which: np.ndarray          # (k,) int64
    rotation: np.ndarray       # (k, 3, 3)
    translation: np.ndarray    # (k, 3) m
    box: np.ndarray            # (k, 2, 3) world bounding box of each copy

    def __len__(self) -> int:
        return len(self.which)


@dataclass(frozen=True)
class SurveyScene:
    """Static triangles (meshes and ground) and plant instances."""

    static: Scene | None
    plants: Plants | None
    bounds: np.ndarray         # (2, 3) m, everything
    build_s: float = 0.0       # CPU time spent building the plant prototypes, s

    @property
    def n_triangles(self) -> int:
        n = 0 if self.static is None else len(self.static)
        if self.plants is not None:
            n += int(sum(len(self.plants.prototypes[w]) for w in self.plants.which))
        return n


def rotation_z(deg) -> np.ndarray:
    """(k, 3, 3) rotations about z by ``deg`` degrees (counter-clockwise)."""
    a = np.radians(np.atleast_1d(np.asarray(deg, np.float64)))
    c, s = np.cos(a), np.sin(a)
    r = np.zeros((len(a), 3, 3))
    r[:, 0, 0], r[:, 0, 1], r[:, 1, 0], r[:, 1, 1], r[:, 2, 2] = c, -s, s, c, 1.0
    return r


DEFAULT_MATERIAL = "default"
"""Material name of OBJ faces before any ``usemtl``."""

_V = re.compile(r"^[ \t]*v[ \t]+([^\r\n#]*)", re.M)  # a comment after the numbers is left out
_F = re.compile(r"^[ \t]*f[ \t]+([^\r\n#]*)", re.M)
_USEMTL = re.compile(r"^[ \t]*usemtl[ \t]+([^\r\n]*?)[ \t]*$", re.M)
_MTLLIB = re.compile(r"^[ \t]*mtllib[ \t]+([^\r\n]*?)[ \t]*$", re.M)


def _starts(pattern: re.Pattern, text: str) -> np.ndarray:
    return np.fromiter((m.start() for m in pattern.finditer(text)), np.int64)


def read_obj(path: Path, materials: dict, source: str) -> Scene:
    """Triangles of an OBJ (polygons fanned, in file order) with each face's material's rho, tau, kind.

    ``materials`` (SCENE.yaml) override the MTL; an MTL material gives rho by
    ``helios_reflectance`` (HELIOS++'s key). A face whose material has neither is an error.
    Parsed with regular expressions over the whole text (no loop over lines in Python).
    """
    try:
        text = path.read_text(errors="replace")
    except OSError as exc:
        raise SurveyError(f"{source}: {path}: cannot read ({exc.strerror or exc})") from None
    parts = _USEMTL.split(text)                  # [before, name 1, body 1, name 2, body 2, ...]
    used, bodies = parts[1::2], parts[0::2]
    per_body = [_F.findall(b) for b in bodies]
    faces = [f for fs in per_body for f in fs]
    if not faces:
        raise SurveyError(f"{source}: {path}: no faces (expected an OBJ with f lines)")
    vlines = _V.findall(text)
    try:
        with warnings.catch_warnings():  # a bad number ends the parse early (a DeprecationWarning)
            warnings.simplefilter("ignore", DeprecationWarning)
            values = np.fromstring(" ".join(vlines), sep=" ") if vlines else np.zeros(0)
        if len(values) == 3 * len(vlines):
            xyz = values.reshape(-1, 3)
        else:  # w or colours after x y z, or a bad number (fromstring stops there)
            xyz = np.array([v.split()[:3] for v in vlines], dtype=np.float64).reshape(-1, 3)
    except ValueError:
        raise SurveyError(f"{source}: {path}: a vertex line is not three numbers") from None
    if not np.all(np.isfinite(xyz)):
        raise SurveyError(f"{source}: {path}: non-finite vertex coordinates")
    corners = re.sub(r"/[^ \t\n]*", "", "\n".join(faces)).split("\n")
    n = np.fromiter((len(c.split()) for c in corners), np.int64, len(corners))
    try:
        flat = np.array(" ".join(corners).split(), dtype=np.int64)
    except ValueError:
        raise SurveyError(f"{source}: {path}: a face line is not vertex indices") from None
    if n.min() < 3:
        raise SurveyError(f"{source}: {path}: a face with fewer than 3 vertices")
    if np.any(flat < 0):  # relative indices count back from the vertices defined so far
        before = np.repeat(np.searchsorted(_starts(_V, text), _starts(_F, text)), n)
        flat = np.where(flat < 0, before + flat, flat - 1)
    else:
        flat = flat - 1
    if flat.min() < 0 or flat.max() >= len(xyz):
        raise SurveyError(f"{source}: {path}: face vertex index out of range (1..{len(xyz)})")
    idx, face = fan_triangles(flat, n)
    which = np.repeat(np.arange(len(bodies)) - 1, [len(fs) for fs in per_body])  # -1: before any usemtl
    names = [DEFAULT_MATERIAL if w < 0 else used[w] for w in np.unique(which)]
    mtl: dict[str, float] = {}
    missing = []
    for lib in _mtl_files(path, _MTLLIB.findall(text)):
        if lib.exists():
            mtl.update(_read_mtl(lib, source))
        else:
            missing.append(lib.name)
    props = np.zeros((len(used) + 1, 3))
    for w, m in zip(np.unique(which), names):
        if m in materials:
            props[w + 1] = _material(materials, m, source)
        elif m in mtl:
            props[w + 1] = (mtl[m], 0.0, KINDS["other"])
        else:
            why = f"; its MTL file {', '.join(missing)} does not exist" if missing else ""
            raise SurveyError(f"{source}: {path}: material {m!r} has no optical properties (expected "
                              f"objects/materials/{m}/rho in the scene file or helios_reflectance in its MTL){why}")
    table = props[which[face] + 1]
    return Scene(xyz[idx].astype(np.float64), table[:, 0], table[:, 1], table[:, 2].astype(np.uint8))


def _material(materials: dict, name: str, source: str) -> tuple[float, float, int]:
    """(rho, tau, kind) of SCENE.yaml's material ``name``; SurveyError for rho + tau > 1."""
    p = materials[name]
    rho, tau = float(p["rho"]), float(p.get("tau", 0.0))
    if rho + tau > 1.0 + 1e-9:
        raise SurveyError(f"{source}: materials/{name}: expected rho + tau <= 1, got {rho + tau:g}")
    return rho, tau, KINDS[p.get("kind", "other")]


def _mtl_files(obj: Path, libs: list[str]) -> list[Path]:
    """The MTL files of ``mtllib`` statements: one name, or several separated by blanks (the
    OBJ specification) unless the whole statement names an existing file."""
    out = []
    for lib in libs:
        whole = obj.parent / lib
        out += [whole] if whole.exists() else [obj.parent / name for name in lib.split()]
    return out


def _read_mtl(path: Path, source: str) -> dict[str, float]:
    """name -> helios_reflectance (in [0, 1]) of an MTL file (materials without it are left out);
    SurveyError naming the file, line and material for a value that is not a reflectance; a
    warning naming the other HELIOS++ keys (``helios_specularity``, ...), which are not used."""
    try:
        lines = path.read_text(errors="replace").splitlines()
    except OSError as exc:
        raise SurveyError(f"{source}: {path}: cannot read ({exc.strerror or exc})") from None
    out, name, ignored = {}, None, {}
    for number, line in enumerate(lines, 1):
        head, *rest = line.split(None, 1) or [""]
        if head == "newmtl":
            name = rest[0].strip() if rest else ""
        elif head == "helios_reflectance" and name is not None:
            try:
                rho = float(rest[0].split()[0]) if rest else math.nan
            except ValueError:
                rho = math.nan
            if not 0.0 <= rho <= 1.0:
                got = repr(rest[0].strip()) if rest else "no value"
                raise SurveyError(f"{source}: {path}: line {number}: helios_reflectance of material {name!r}: "
                                  f"expected a number in [0, 1], got {got}")
            out[name] = rho
        elif head.startswith("helios_") and head != "helios_reflectance":
            ignored.setdefault(head, number)
    if ignored:
        warnings.warn(f"{path}: {', '.join(f'{k} (line {n})' for k, n in ignored.items())}: not used (surfaces are "
                      "Lambertian with the reflectance of helios_reflectance, or the rho and tau of SCENE.yaml)",
                      WaveforestWarning, stacklevel=2)
    return out


def read_mesh(path: Path, materials: dict, source: str) -> Scene:
    """A PLY (rho, tau, kind per face, or the material ``default`` of ``materials`` for a PLY
    without them) or OBJ + MTL mesh; SurveyError naming the file."""
    if not path.exists():
        raise SurveyError(f"{source}: {path}: no such file")
    if path.suffix.lower() == ".obj":
        return read_obj(path, materials, source)
    default = _material(materials, DEFAULT_MATERIAL, source) if DEFAULT_MATERIAL in materials else None
    try:
        return read_ply(path, default)
    except SceneError as exc:
        hint = f"; or set this object's materials/{DEFAULT_MATERIAL}/rho for every face" if (
            default is None and "face property" in str(exc)) else ""
        raise SurveyError(f"{source}: {exc}{hint}") from None


def _place(scene: Scene, scale: float, rotate_deg: float, translate) -> Scene:
    r = rotation_z(rotate_deg)[0]
    tri = (scene.triangles.astype(np.float64) * scale) @ r.T + np.asarray(translate, np.float64)
    return Scene(tri, scene.rho, scene.tau, scene.kind)


PLANT_COLUMNS = ("species", "x", "y", "height", "seed", "z", "rotation_deg")
"""Columns of the plant CSV: the five required, then the optional."""


def plant_table(path: Path, source: str) -> pd.DataFrame:
    """The plant CSV: species, x, y, height, seed (+ z, rotation_deg, default 0)."""
    if not path.exists():
        raise SurveyError(f"{source}: plants/table: {path}: no such file")
    try:
        df = pd.read_csv(path, skipinitialspace=True)
    except Exception as exc:  # pandas raises several types on malformed CSV
        raise SurveyError(f"{source}: plants/table: {path}: not a readable CSV ({exc})") from None
    df.columns = [str(c).strip() for c in df.columns]
    missing = [c for c in PLANT_COLUMNS[:5] if c not in df.columns]
    if missing:
        raise SurveyError(f"{path}: missing column(s) {', '.join(missing)} (expected {', '.join(PLANT_COLUMNS[:5])}, "
                          f"optional {', '.join(PLANT_COLUMNS[5:])}; found {', '.join(df.columns)})")
    unknown = [c for c in df.columns if c not in PLANT_COLUMNS]
    if unknown:
        raise SurveyError(f"{path}: unknown column(s) {', '.join(unknown)} (expected {', '.join(PLANT_COLUMNS[:5])}, "
                          f"optional {', '.join(PLANT_COLUMNS[5:])})")
    if not len(df):
        raise SurveyError(f"{path}: no plant rows (expected one row per plant under the header)")
    if "rotation_deg" not in df.columns:
        df["rotation_deg"] = 0.0
    on_ground = "z" not in df.columns
    if on_ground:  # placed on the ground by load_scene
        df["z"] = 0.0
    for c in ("x", "y", "z", "height", "rotation_deg"):
        v = pd.to_numeric(df[c], errors="coerce").to_numpy(np.float64)
        if not np.all(np.isfinite(v)):
            raise SurveyError(f"{path}: column {c}, row {int(np.flatnonzero(~np.isfinite(v))[0]) + 2}: "
                              "expected a finite number")
        df[c] = v
    bad = np.flatnonzero(~(df["height"].to_numpy() > 0))
    if bad.size:
        raise SurveyError(f"{path}: column height, row {int(bad[0]) + 2}: expected a height above 0 m, got "
                          f"{df['height'].iloc[bad[0]]:g}")
    seed = pd.to_numeric(df["seed"], errors="coerce").to_numpy(np.float64)
    bad = np.flatnonzero(~((seed >= 0) & (seed == np.round(seed))))
    if bad.size:
        raise SurveyError(f"{path}: column seed, row {int(bad[0]) + 2}: expected a non-negative integer, got "
                          f"{str(df['seed'].iloc[bad[0]])!r}")
    df["seed"] = seed.astype(np.int64)
    df.attrs["on_ground"] = on_ground
    return df


def _plants(df: pd.DataFrame, seeds: int, step: float, source: str, progress: bool = False) -> Plants:
    """Prototypes of the plant rows: heights rounded to ``step`` within their species' range."""
    lo, hi = np.empty(len(df)), np.empty(len(df))
    for sp, heights in df.groupby(df["species"].astype(str))["height"]:
        try:
            p = species_params(sp)
        except WaveforestError as exc:
            raise SurveyError(f"{source}: plants/table: {exc}") from None
        out = heights[(heights < p.h_min_ok) | (heights > p.h_max_ok)]
        if len(out):
            raise SurveyError(f"{source}: plants/table: row {int(out.index[0]) + 2}: height {out.iloc[0]:g} m for "
                              f"{sp}: expected {p.h_min_ok:g} to {p.h_max_ok:g} m")
        rows = df.index.get_indexer(heights.index)
        lo[rows], hi[rows] = p.h_min_ok, p.h_max_ok
    h = np.clip(np.round(df["height"].to_numpy() / step) * step, lo, hi)
    s = df["seed"].to_numpy(np.int64) % seeds
    keys = list(zip(df["species"].astype(str), h.round(6), s))
    uniq = sorted(set(keys))
    index = {k: i for i, k in enumerate(uniq)}
    protos = []
    todo = uniq
    if progress:
        from tqdm import tqdm

        todo = tqdm(uniq, desc="plant prototypes", unit="prototype")
    for sp, hh, ss in todo:
        try:
            protos.append(build(sp, float(hh), int(ss), ground=False).scene)
        except WaveforestError as exc:
            raise SurveyError(f"{source}: plants/table: {exc}") from None
    which = np.array([index[k] for k in keys], np.int64)
    rot = rotation_z(df["rotation_deg"].to_numpy())
    t = df[["x", "y", "z"]].to_numpy(np.float64)
    pb = np.stack([p.bounds for p in protos])[which]                    # (k, 2, 3) local
    corners = np.stack([pb[:, [i, j, c], [0, 1, 2]] for i in (0, 1) for j in (0, 1) for c in (0, 1)], axis=1)
    placed = np.einsum("kab,kcb->kca", rot, corners) + t[:, None, :]
    box = np.stack([placed.min(axis=1), placed.max(axis=1)], axis=1)
    return Plants(tuple(protos), tuple(f"{a} {b:g} m seed {c}" for a, b, c in uniq), which, rot, t, box)


def ground_height(ground: Scene, xy: np.ndarray, source: str) -> np.ndarray:
    """(n,) height of the ground mesh's highest face above each point ``xy`` (n, 2), m: where
    a vertical ray from above first meets it; SurveyError for a point beyond the mesh."""
    prepared = prepare(ground, quality="low")
    top = float(prepared.bounds[1, 2]) + 1.0
    org = np.column_stack([xy - prepared.shift[:2], np.full(len(xy), top)]).astype(np.float32)
    down = np.tile(np.float32([0.0, 0.0, -1.0]), (len(xy), 1))
    t, prim = prepared.intersector.intersect(org, down)
    miss = np.flatnonzero(prim < 0)
    if miss.size:
        x, y = xy[miss[0]]
        raise SurveyError(f"{source}: row {int(miss[0]) + 2}: ({x:g}, {y:g}) lies beyond the ground mesh "
                          "(expected a plant over the ground, or a z column)")
    return prepared.shift[2] + top - t.astype(np.float64)


def load_scene(path: str | Path, progress: bool = False) -> SurveyScene:
    """Read SCENE.yaml and everything it names (SurveyError: file, field, what was expected);
    ``progress``: a bar over the plant prototypes built."""
    path = Path(path)
    doc = read_document(path, SCENE_SCHEMA)
    base, src = path.parent, str(path)
    parts = []
    for i, o in enumerate(doc["objects"]):
        mesh = read_mesh(base / o["file"], o["materials"], f"{src}: objects/{i}")
        parts.append(_place(mesh, float(o["scale"]), float(o["rotate_deg"]), o["translate"]))
    g = doc["ground"]
    ground = None
    if g["type"] == "mesh":
        if g["file"] is None:
            raise SurveyError(f"{src}: ground/file: expected a mesh file for ground type mesh")
        # faces without properties of their own (a bare PLY, OBJ faces before any usemtl) take ground/rho
        mesh = read_mesh(base / g["file"], {DEFAULT_MATERIAL: {"rho": float(g["rho"])}}, f"{src}: ground")
        ground = Scene(mesh.triangles, mesh.rho, mesh.tau, KIND_GROUND)  # every face is ground
        parts.append(ground)
    pl = doc["plants"]
    plants, build_s = None, 0.0
    if pl["table"] is not None:
        df = plant_table(base / pl["table"], src)
        if len(df):
            if df.attrs["on_ground"] and g["type"] != "none":
                df["z"] = (np.full(len(df), float(g["z"])) if ground is None else
                           ground_height(ground, df[["x", "y"]].to_numpy(), f"{src}: plants/table"))
            cpu = time.process_time()
            plants = _plants(df, int(pl["prototype_seeds"]), float(pl["height_step_m"]), src, progress)
            build_s = time.process_time() - cpu
    plant_box = [] if plants is None else [np.stack([plants.box[:, 0].min(axis=0), plants.box[:, 1].max(axis=0)])]
    boxes = [p.bounds for p in parts] + plant_box
    if g["type"] == "plane":
        if g["extent"] is not None:
            x0, y0, x1, y1 = map(float, g["extent"])
        elif boxes:
            lo = np.min([b[0] for b in boxes], axis=0)
            hi = np.max([b[1] for b in boxes], axis=0)
            m = float(g["margin_m"])
            x0, y0, x1, y1 = lo[0] - m, lo[1] - m, hi[0] + m, hi[1] + m
        else:
            raise SurveyError(f"{src}: ground/extent: expected an extent for a ground plane with no objects or plants")
        if not (x1 > x0 and y1 > y0):
            raise SurveyError(f"{src}: ground/extent: expected xmin < xmax and ymin < ymax")
        parts.append(ground_plane(x0, y0, x1, y1, float(g["z"]), float(g["rho"])))
    static = Scene.concat(parts) if parts else None
    if static is None and plants is None:
        raise SurveyError(f"{src}: the scene is empty (expected objects, plants or a ground)")
    allb = ([static.bounds] if static is not None else []) + plant_box
    bounds = np.stack([np.min([b[0] for b in allb], axis=0), np.max([b[1] for b in allb], axis=0)])
    return SurveyScene(static, plants, bounds, build_s)


def ground_plane(x0: float, y0: float, x1: float, y1: float, z: float, rho: float) -> Scene:
    """Two upward-facing triangles covering [x0, x1] x [y0, y1] at height z."""
    a, b, c, d = (x0, y0, z), (x1, y0, z), (x1, y1, z), (x0, y1, z)
    return Scene(np.array([[a, b, c], [a, c, d]], np.float64), rho, 0.0, KIND_GROUND)


def input_files(scene_path: str | Path, survey_path: str | Path) -> list[str]:
    """The files SCENE.yaml and SURVEY.yaml name that exist (meshes with an OBJ's MTL files,
    plant table, trajectory, S(t)): a workflow's inputs, so that editing one reruns the survey,
    and the files an output folder must not hold. A file that cannot be read gives none (the
    survey's own run reports it)."""
    out = []
    try:
        scene, survey = read_document(scene_path, SCENE_SCHEMA), read_document(survey_path, SURVEY_SCHEMA)
    except SurveyError:
        return out
    names = ([(scene_path, o["file"]) for o in scene["objects"]]
             + [(scene_path, scene["ground"]["file"]), (scene_path, scene["plants"]["table"]),
                (survey_path, survey["platform"]["trajectory"]), (survey_path, survey["scanner"]["system_waveform"])])
    for doc, name in names:
        path = resolve(Path(doc).parent, name)
        if path is not None and path.exists():
            out.append(str(path))
            if path.suffix.lower() == ".obj":
                with suppress(OSError):
                    libs = _MTLLIB.findall(path.read_text(errors="replace"))
                    out += [str(m) for m in _mtl_files(path, libs) if m.exists()]
    return out
