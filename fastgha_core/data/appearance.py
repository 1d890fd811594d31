"""Procedural appearance of synthetic heads: regions, albedo, hair shell and baked lighting.

Everything is per vertex of the ICT-FaceKit mesh (``headmodel.py``), computed on the *generic*
neutral mesh so that regions are the same for every identity and move with expressions:

- ``HeadRegions`` (once per head model): soft vertex masks for lips, brows, mouth interior,
  eye sockets, teeth, gums/tongue, eyelashes, eyeball angles, and a vertex adjacency for smoothing.
- ``AppearanceParams.sample(rng)``: one subject's looks (skin tone from a wide range, blotches,
  fine texture, lips, brows, iris colour, hair colour/hairline/length/volume, lighting).
- ``subject_albedo``: per-vertex albedo ``[Nv, 3]`` of the skin mesh and ``[Nv, 3]`` of the hair
  shell, plus per-vertex hair thickness ``[Nv]`` in metres.
- ``shade``: baked lighting (key light with a colour temperature, fill, hemispherical ambient,
  wrapped Lambert and a little Blinn-Phong specular). The specular uses a *fixed* viewer at +z so
  the shading is view-independent: every camera of a timestep sees the same colours, as a
  Gaussian avatar with RGB colours would.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from matplotlib.path import Path as PolyPath
from scipy.ndimage import map_coordinates

from .headmodel import EYEBALL_VERTEX_RANGE, HEAD_VERTEX_RANGE, SOCKET_VERTEX_RANGE, HeadModel

__all__ = ["HeadRegions", "AppearanceParams", "head_regions", "subject_albedo", "shade", "hair_shell_faces"]


def _smoothstep(x):
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)


# ---------------------------------------------------------------------------- regions
@dataclass(eq=False)
class HeadRegions:
    """Soft per-vertex masks ``[Nv]`` in [0, 1] on the generic neutral mesh."""

    adjacency: sp.csr_matrix  # [Nv, Nv] row-normalised vertex adjacency (for smoothing)
    skin: np.ndarray  # face, head and neck
    lips: np.ndarray
    brows: np.ndarray
    brow_core: np.ndarray  # 1 near the inner brow, 0 at the tail (for tapering)
    mouth_interior: np.ndarray  # mouth socket, gums, tongue; value = how deep (0..1)
    eye_socket: np.ndarray
    teeth: np.ndarray
    gums: np.ndarray
    lashes: np.ndarray
    eyeball: np.ndarray
    eye_angle: np.ndarray  # angle (rad) from the eyeball's optical axis, eyeball vertices only
    eye_azimuth: np.ndarray  # angle around the optical axis (rad), eyeball vertices only
    cheeks: np.ndarray  # soft blobs on cheeks and nose (redness)
    phi: np.ndarray  # azimuth about the vertical axis, 0 = front, +/-pi = back
    theta: np.ndarray  # elevation angle from the head centre
    head_faces: np.ndarray  # [Fh] ids of skin triangles (M_Face, M_BackHead)

    def smooth(self, x: np.ndarray, iterations: int) -> np.ndarray:
        """Average ``x [Nv, ...]`` over mesh neighbours ``iterations`` times."""
        for _ in range(iterations):
            x = self.adjacency @ x
        return x


@functools.lru_cache(maxsize=2)
def head_regions(model: HeadModel) -> HeadRegions:
    """Region masks of ``model`` (cached per model object)."""
    v = model.neutral.astype(np.float64)  # [Nv, 3] metres, centred
    nv = v.shape[0]
    faces = model.faces
    lm = v[model.landmarks68]  # [68, 3]

    rows = np.concatenate([faces[:, 0], faces[:, 1], faces[:, 2], faces[:, 1], faces[:, 2], faces[:, 0]])
    cols = np.concatenate([faces[:, 1], faces[:, 2], faces[:, 0], faces[:, 0], faces[:, 1], faces[:, 2]])
    A = sp.coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(nv, nv)).tocsr()
    A.data[:] = 1.0
    A = A + sp.identity(nv, format="csr")
    A = sp.diags(1.0 / np.asarray(A.sum(axis=1)).ravel()) @ A
    adjacency = A.tocsr()

    def smooth(x, it):
        for _ in range(it):
            x = adjacency @ x
        return x

    idx = np.arange(nv)
    skin = ((idx >= HEAD_VERTEX_RANGE[0]) & (idx < HEAD_VERTEX_RANGE[1])).astype(np.float64)
    front = skin * (v[:, 2] > 0.03)

    lips_hard = PolyPath(lm[48:60, :2]).contains_points(v[:, :2]) * front
    lips = np.clip(smooth(lips_hard.astype(np.float64), 2) * 1.3, 0, 1) * skin

    brows = np.zeros(nv)
    brow_core = np.zeros(nv)
    for side in (lm[17:22], lm[22:27]):
        inner_first = side if abs(side[-1, 0]) < abs(side[0, 0]) else side[::-1]  # index 0 = tail
        inner_first = inner_first[::-1]  # index 0 = inner end
        d_best = np.full(nv, np.inf)
        s_best = np.zeros(nv)
        for k in range(4):
            a, b = inner_first[k, :2], inner_first[k + 1, :2]
            ab = b - a
            t = np.clip(((v[:, :2] - a) @ ab) / (ab @ ab), 0, 1)
            d = np.linalg.norm(v[:, :2] - (a + t[:, None] * ab), axis=1)
            better = d < d_best
            d_best = np.where(better, d, d_best)
            s_best = np.where(better, (k + t) / 4.0, s_best)
        ok = (v[:, 2] > inner_first[:, 2].min() - 0.02) & (skin > 0)
        width = 0.0075 - 0.0045 * s_best  # half-width tapers from inner end to tail
        m = _smoothstep((width - d_best) / 0.002 + 0.5) * ok
        brows = np.maximum(brows, m)
        brow_core = np.maximum(brow_core, m * (1.0 - s_best))

    sock = (idx >= SOCKET_VERTEX_RANGE[0]) & (idx < SOCKET_VERTEX_RANGE[1])
    eye_level = 0.5 * (lm[36:48, 1].mean() + lm[27, 1])
    mouth_socket = sock & (v[:, 1] < eye_level - 0.02)
    eye_socket = (sock & ~mouth_socket).astype(np.float64)
    gums = model.material_mask("M_GumsTongue")
    gum_v = np.zeros(nv, bool)
    gum_v[np.unique(faces[gums])] = True
    teeth_v = np.zeros(nv, bool)
    teeth_v[np.unique(faces[model.material_mask("M_Teeth")])] = True
    lips_front_z = lm[48:68, 2].max()
    depth_in = np.clip((lips_front_z - v[:, 2]) / 0.05, 0, 1)  # 0 at the lips, 1 at 5 cm behind
    mouth_interior = np.where(mouth_socket | gum_v, 0.25 + 0.75 * depth_in, 0.0)
    lashes = np.zeros(nv)
    lashes[np.unique(faces[model.material_mask("M_EyeLashes")])] = 1.0

    eyeball = np.zeros(nv)
    eye_angle = np.full(nv, np.pi)
    eye_az = np.zeros(nv)
    for sclera, iris in (("M_ScleraLeft", "M_IrisLeft"), ("M_ScleraRight", "M_IrisRight")):
        sv = np.unique(faces[model.material_mask(sclera)])
        allv = np.unique(faces[model.material_mask(sclera, iris)])
        p = v[sv]
        M = np.c_[2 * p, np.ones(len(p))]
        sol = np.linalg.lstsq(M, (p**2).sum(1), rcond=None)[0]
        c = sol[:3]
        axis = p[p[:, 2].argmax()] - c
        axis /= np.linalg.norm(axis)
        d = v[allv] - c
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        eye_angle[allv] = np.arccos(np.clip(d @ axis, -1, 1))
        ex = np.cross([0.0, 1.0, 0.0], axis)
        ex /= np.linalg.norm(ex)
        ey = np.cross(axis, ex)
        eye_az[allv] = np.arctan2(d @ ey, d @ ex)
        eyeball[allv] = 1.0
    assert EYEBALL_VERTEX_RANGE[0] <= int(np.flatnonzero(eyeball).min())

    cheeks = np.zeros(nv)
    for centre, radius in ((0.5 * (lm[1] + lm[31]), 0.025), (0.5 * (lm[15] + lm[35]), 0.025), (lm[30], 0.015)):
        cheeks = np.maximum(cheeks, np.exp(-np.sum((v - centre) ** 2, axis=1) / (2 * radius**2)))
    cheeks *= skin

    phi = np.arctan2(v[:, 0], v[:, 2])
    theta = np.arctan2(v[:, 1], np.hypot(v[:, 0], v[:, 2]))
    head_faces = np.flatnonzero(model.material_mask("M_Face", "M_BackHead"))
    return HeadRegions(
        adjacency=adjacency,
        skin=skin,
        lips=lips,
        brows=brows,
        brow_core=brow_core,
        mouth_interior=mouth_interior,
        eye_socket=eye_socket,
        teeth=teeth_v.astype(np.float64),
        gums=gum_v.astype(np.float64),
        lashes=lashes,
        eyeball=eyeball,
        eye_angle=eye_angle,
        eye_azimuth=eye_az,
        cheeks=cheeks,
        phi=phi,
        theta=theta,
        head_faces=head_faces,
    )


# ---------------------------------------------------------------------------- parameters
_SKIN_RAMP = np.array(  # light -> very dark, sRGB albedo
    [[0.96, 0.80, 0.70], [0.88, 0.68, 0.55], [0.76, 0.55, 0.40], [0.58, 0.39, 0.27], [0.40, 0.26, 0.18], [0.24, 0.15, 0.10]]
)
_HAIR_COLOURS = np.array(  # black, dark brown, brown, auburn, dark blond, blond, grey, white-grey
    [[0.035, 0.030, 0.028], [0.09, 0.06, 0.04], [0.22, 0.14, 0.08], [0.40, 0.16, 0.07], [0.50, 0.38, 0.22],
     [0.78, 0.64, 0.42], [0.45, 0.44, 0.43], [0.80, 0.79, 0.77]]
)
_HAIR_WEIGHTS = np.array([0.26, 0.24, 0.18, 0.06, 0.09, 0.07, 0.06, 0.04])
_IRIS_COLOURS = np.array([[0.20, 0.11, 0.05], [0.35, 0.20, 0.08], [0.30, 0.35, 0.18], [0.25, 0.40, 0.55], [0.40, 0.50, 0.60], [0.12, 0.07, 0.04]])


def _colour_temperature(kelvin: float) -> np.ndarray:
    """Approximate linear RGB of a black body at ``kelvin`` (normalised to max 1)."""
    t = kelvin / 100.0
    r = 1.0 if t <= 66 else 1.292936 * (t - 60) ** -0.1332047
    g = 0.39008158 * math.log(t) - 0.63184144 if t <= 66 else 1.129890 * (t - 60) ** -0.0755148
    b = 1.0 if t >= 66 else (0.0 if t <= 19 else 0.54320679 * math.log(t - 10) - 1.19625409)
    rgb = np.clip([r, g, b], 0.05, 1.0) ** 2.2
    return rgb / rgb.max()


@dataclass
class AppearanceParams:
    """One subject's procedural looks and lighting (all drawn by ``sample``)."""

    skin: np.ndarray  # [3] base skin albedo (sRGB)
    redness: float  # strength of red blotches on cheeks/nose
    blotch: float  # amplitude of low-frequency skin variation
    grain: float  # amplitude of fine per-vertex texture
    lip: np.ndarray  # [3] lip albedo
    brow: np.ndarray  # [3] brow colour
    brow_density: float
    iris: np.ndarray  # [3]
    hair: np.ndarray  # [3]
    hair_front: float  # forehead hairline height above the brows (m)
    hair_side: float  # hairline height at the ears (m, relative to the head centre)
    hair_back: float  # hairline height at the nape (m); lower = longer hair
    hair_temple: float  # temple recession (m)
    hair_thickness: float  # shell thickness (m)
    hair_streak: float  # strand contrast
    key_dir: np.ndarray  # [3] unit vector towards the key light (world)
    key_rgb: np.ndarray  # [3] key light colour x intensity (linear)
    fill_rgb: np.ndarray  # [3]
    ambient_rgb: np.ndarray  # [3]
    specular: float
    noise_seed: int

    @staticmethod
    def sample(rng: np.random.Generator) -> "AppearanceParams":
        t = rng.uniform(0, 1) ** 0.9 * (len(_SKIN_RAMP) - 1)
        k = min(int(t), len(_SKIN_RAMP) - 2)
        skin = _SKIN_RAMP[k] * (1 - (t - k)) + _SKIN_RAMP[k + 1] * (t - k)
        skin = skin * np.array([1.0 + rng.normal(0, 0.03), 1.0 + rng.normal(0, 0.03), 1.0 + rng.normal(0, 0.05)])
        lip = skin * np.array([0.92, 0.62, 0.62]) * rng.uniform(0.8, 1.05) + np.array([0.06, 0.0, 0.01]) * rng.uniform(0, 1)
        hair = _HAIR_COLOURS[rng.choice(len(_HAIR_COLOURS), p=_HAIR_WEIGHTS)] * rng.uniform(0.8, 1.2, size=3) ** 0.3
        brow = np.minimum(hair * rng.uniform(0.5, 0.9), skin * 0.45)
        az = math.radians(rng.uniform(-75, 75))
        el = math.radians(rng.uniform(-5, 60))
        key_dir = np.array([math.cos(el) * math.sin(az), math.sin(el), math.cos(el) * math.cos(az)])
        key_rgb = _colour_temperature(rng.uniform(2800, 7500)) * rng.uniform(0.7, 1.1)
        fill_rgb = _colour_temperature(rng.uniform(4500, 9000)) * rng.uniform(0.05, 0.25)
        ambient_rgb = _colour_temperature(rng.uniform(4000, 9000)) * rng.uniform(0.2, 0.45)
        return AppearanceParams(
            skin=np.clip(skin, 0.05, 1.0),
            redness=float(rng.uniform(0.0, 0.12)),
            blotch=float(rng.uniform(0.02, 0.06)),
            grain=float(rng.uniform(0.015, 0.04)),
            lip=np.clip(lip, 0.03, 1.0),
            brow=brow,
            brow_density=float(rng.uniform(0.7, 1.0)),
            iris=_IRIS_COLOURS[rng.integers(len(_IRIS_COLOURS))] * rng.uniform(0.8, 1.2),
            hair=np.clip(hair, 0.0, 1.0),
            hair_front=float(rng.uniform(0.040, 0.068)),
            hair_side=float(rng.uniform(-0.05, 0.03)),
            hair_back=float(rng.uniform(-0.20, -0.06)),
            hair_temple=float(rng.uniform(0.0, 0.006)),
            hair_thickness=float(rng.uniform(0.004, 0.025)),
            hair_streak=float(rng.uniform(0.15, 0.4)),
            key_dir=key_dir,
            key_rgb=key_rgb,
            fill_rgb=fill_rgb,
            ambient_rgb=ambient_rgb,
            specular=float(rng.uniform(0.03, 0.12)),
            noise_seed=int(rng.integers(0, 2**31 - 1)),
        )


# ---------------------------------------------------------------------------- noise
def _lattice_noise(points: np.ndarray, rng: np.random.Generator, cell: float, order: int = 3) -> np.ndarray:
    """Smooth random field at ``points [N, D]`` (D = 2 or 3), ~unit variance, feature size ``cell``."""
    lo = points.min(axis=0) - 2 * cell
    hi = points.max(axis=0) + 2 * cell
    shape = tuple(int(np.ceil(s)) + 1 for s in (hi - lo) / cell)
    grid = rng.standard_normal(shape)
    coords = ((points - lo) / cell).T
    out = map_coordinates(grid, coords, order=order, mode="nearest")
    return out / max(float(out.std()), 1e-6)


# ---------------------------------------------------------------------------- albedo
@dataclass
class SubjectAlbedo:
    skin: np.ndarray  # [Nv, 3] albedo of the mesh (sRGB, [0, 1])
    hair: np.ndarray  # [Nv, 3] albedo of the hair shell vertices
    hair_weight: np.ndarray  # [Nv] 1 where the scalp is under hair
    hair_thickness: np.ndarray  # [Nv] metres of shell offset along the normal
    specular: np.ndarray  # [Nv] specular strength
    shininess: np.ndarray  # [Nv] Blinn-Phong exponent


def hair_shell_faces(model: HeadModel, regions: HeadRegions, hair_weight: np.ndarray) -> np.ndarray:
    """``[Fs, 3]`` skin triangles under hair (all three corners with weight > 0.02)."""
    f = model.faces[regions.head_faces]
    keep = (hair_weight[f] > 0.02).all(axis=1)
    return f[keep]


def subject_albedo(model: HeadModel, params: AppearanceParams) -> SubjectAlbedo:
    """Per-vertex albedo of one subject (deterministic for ``params``)."""
    reg = head_regions(model)
    rng = np.random.default_rng(params.noise_seed)
    v = model.neutral.astype(np.float64)
    nv = v.shape[0]
    lm = v[model.landmarks68]

    # skin: base, low-frequency blotches, redness on cheeks/nose, fine grain
    low = _lattice_noise(v, rng, 0.03)
    mid = _lattice_noise(v, rng, 0.01)
    grain = reg.smooth(rng.standard_normal(nv), 1)
    grain /= grain.std()
    shade = 1.0 + params.blotch * low + 0.4 * params.blotch * mid + params.grain * grain
    albedo = params.skin[None, :] * shade[:, None]
    red = params.redness * (reg.cheeks + 0.4 * np.clip(mid, 0, None) * reg.skin)
    albedo = albedo * (1 - red[:, None]) + red[:, None] * params.skin * np.array([1.05, 0.55, 0.55])
    # lips
    lipw = reg.lips[:, None]
    albedo = albedo * (1 - lipw) + lipw * params.lip[None, :] * (1.0 + 0.05 * grain[:, None])
    # brows: density x strand noise x taper
    strands = _lattice_noise(v[:, :2] * np.array([1.0, 3.0]), rng, 0.002, order=1)
    bw = reg.brows * params.brow_density * np.clip(0.85 + 0.15 * strands, 0, 1) * (0.7 + 0.3 * reg.brow_core)
    albedo = albedo * (1 - bw[:, None]) + bw[:, None] * params.brow[None, :]
    # eye sockets, mouth interior, gums/tongue, teeth, lashes
    es = reg.eye_socket[:, None]
    albedo = albedo * (1 - es) + es * params.skin * np.array([0.75, 0.5, 0.5])
    mi = reg.mouth_interior
    gum_col = np.array([0.72, 0.33, 0.33]) * (1.0 - 0.75 * mi)[:, None]
    sock_col = np.array([0.30, 0.10, 0.10]) * (1.0 - 0.8 * mi)[:, None]
    mouthw = (mi > 0)[:, None]
    albedo = np.where(mouthw & (reg.gums[:, None] > 0), gum_col, np.where(mouthw, sock_col, albedo))
    depth_in = np.clip((lm[48:68, 2].max() - v[:, 2]) / 0.045, 0, 1)
    teeth_col = np.array([0.90, 0.87, 0.78]) * (1.0 - 0.8 * depth_in)[:, None] * (1.0 + 0.03 * grain[:, None])
    albedo = np.where(reg.teeth[:, None] > 0, teeth_col, albedo)
    albedo = np.where(reg.lashes[:, None] > 0, 0.5 * params.brow + 0.5 * params.skin * 0.45, albedo)
    # eyes: pupil, iris with radial streaks and a dark limbal ring, sclera
    ang = reg.eye_angle
    iris_r, pupil_r = 0.36, 0.13
    radial = np.cos(reg.eye_azimuth * 23.0) * 0.5 + 0.5
    iris_col = params.iris * (0.75 + 0.4 * radial[:, None]) * (0.7 + 0.5 * ((ang - pupil_r) / (iris_r - pupil_r)))[:, None]
    limbal = _smoothstep((ang - (iris_r - 0.06)) / 0.06)[:, None]
    iris_col = iris_col * (1 - 0.5 * limbal)
    sclera_col = np.array([0.86, 0.82, 0.80]) * (1.0 - 0.25 * _smoothstep((ang - 0.8) / 0.7))[:, None]
    eye_col = np.where((ang < pupil_r)[:, None], 0.02, np.where((ang < iris_r)[:, None], iris_col, sclera_col))
    albedo = np.where(reg.eyeball[:, None] > 0, eye_col, albedo)

    # hair: hairline height as a function of the azimuth phi about the vertical axis
    a = np.abs(reg.phi)
    brow_y = float(lm[17:27, 1].max())
    y_front = brow_y + params.hair_front
    phi0 = math.radians(62.0)
    temple = params.hair_temple * np.exp(-((a - 0.7) ** 2) / (2 * 0.35**2))
    s1 = _smoothstep((a - phi0) / (math.pi / 2 - phi0))
    s2 = _smoothstep((a - math.pi / 2) / (math.pi / 2))
    y_line = np.where(a < math.pi / 2, y_front + (params.hair_side - y_front) * s1, params.hair_side + (params.hair_back - params.hair_side) * s2)
    y_line = y_line + temple + 0.004 * _lattice_noise(np.c_[reg.phi], rng, 0.15)
    hair_w = _smoothstep((v[:, 1] - y_line) / 0.012 + 0.5) * reg.skin
    thick_noise = 1.0 + 0.25 * _lattice_noise(v, rng, 0.04)
    hair_thick = params.hair_thickness * _smoothstep((v[:, 1] - y_line) / 0.03) * thick_noise * reg.skin
    hair_thick = hair_thick + 0.0008 * hair_w
    strand = _lattice_noise(np.c_[reg.phi * 0.09 / 0.0015, reg.theta * 0.09 / 0.02], rng, 1.0, order=1)
    clump = _lattice_noise(v, rng, 0.03)
    hair_col = params.hair[None, :] * (1.0 + params.hair_streak * strand[:, None] + 0.1 * clump[:, None])
    skin_only = albedo
    albedo = albedo * (1 - 0.9 * hair_w[:, None]) + 0.9 * hair_w[:, None] * hair_col * 0.8
    edge = np.clip(hair_w * 1.5, 0, 1)[:, None]  # the shell fades into the skin at the hairline
    shell_col = skin_only * (1 - edge) + hair_col * edge

    spec = np.full(nv, params.specular) * (1 - hair_w) + 0.12 * hair_w
    spec = spec + 0.15 * reg.lips + 0.5 * reg.eyeball + 0.1 * reg.teeth
    shin = np.where(reg.eyeball > 0, 120.0, np.where(reg.lips > 0.5, 40.0, 18.0))
    return SubjectAlbedo(
        skin=np.clip(albedo, 0, 1).astype(np.float32),
        hair=np.clip(shell_col, 0, 1).astype(np.float32),
        hair_weight=hair_w.astype(np.float32),
        hair_thickness=hair_thick.astype(np.float32),
        specular=spec.astype(np.float32),
        shininess=shin.astype(np.float32),
    )


# ---------------------------------------------------------------------------- lighting
def shade(
    albedo: np.ndarray,  # [N, 3] sRGB albedo
    normals: np.ndarray,  # [N, 3] unit normals (world)
    specular: np.ndarray,  # [N]
    shininess: np.ndarray,  # [N]
    params: AppearanceParams,
    exposure: float = 1.0,
) -> np.ndarray:
    """Baked, view-independent lighting -> sRGB colours ``[N, 3]`` in [0, 1] (float32)."""
    lin = np.asarray(albedo, dtype=np.float64) ** 2.2
    n = np.asarray(normals, dtype=np.float64)
    key = params.key_dir
    wrap = 0.25
    ndl = np.clip((n @ key + wrap) / (1 + wrap), 0, None)[:, None]
    fill_dir = np.array([-key[0], 0.2, abs(key[2])])
    fill_dir /= np.linalg.norm(fill_dir)
    ndf = np.clip(n @ fill_dir, 0, None)[:, None]
    hemi = (0.65 + 0.35 * (0.5 + 0.5 * n[:, 1]))[:, None]
    rad = lin * (params.ambient_rgb * hemi + params.key_rgb * ndl + params.fill_rgb * ndf)
    h = key + np.array([0.0, 0.0, 1.0])
    h /= np.linalg.norm(h)
    spec = (np.clip(n @ h, 0, None) ** shininess * specular)[:, None] * params.key_rgb
    out = (rad + spec) * exposure
    out = out / (1.0 + 0.15 * out)  # gentle highlight roll-off
    return np.clip(out, 0, 1) ** (1 / 2.2)
