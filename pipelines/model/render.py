"""The one forward model (DESIGN §3): every solver and every render goes through `transport`.

    I_j = sum_i L_i w_i V_ij max(0, N_j . d_i) f_j(d_i, v_j)

with L_i the radiance of light texel i, w_i its exact solid angle, V_ij its visibility, N_j the
shading normal, v_j the direction to the camera and f the BRDF:
    lambert       f = kd / pi
    blinn-phong   f = kd / pi + ks (n + 8) / (8 pi) max(0, N . H)^n,  H = normalize(d + v)
    phong         f = kd / pi + ks (n + 2) / (2 pi) max(0, R . d)^n,  R = reflect(v, N)
    phong-classic f = kd / pi + ks max(0, R . d)^n / max(N . d, eps)  (the paper's unnormalised
                  term: its radiance contribution is ks (R.d)^n L w, without the cosine)
    plastic       f = ks F(v.h) D(h) G1(v) G1(d) / (4 N.v N.d) + kd t(N.v) t(N.d) / (pi eta^2 (1 - Fdr))
                  (Mitsuba's roughplastic / plastic; `pipelines.model.microfacet`)
kd and ks are RGB; the transport splits into a diffuse part D (kd = 1) and a specular part S
(ks = 1) so that channel c renders kd_c D L_c + ks_c S L_c.
"""

from __future__ import annotations

import numpy as np

from ..geometry.visibility import VisibilityData
from ..light.cubemap import CubeMap
from ..threads import parallel_blocks
from . import microfacet as mf
from .materials import PLASTIC, Material

KERNEL_ROWS = 256  # rows per block of the transport kernels: a block's scratch stays in cache
SPARSE_LIGHT_SHARE = 0.5  # `render` forms the lit texels' columns alone when at most this share is lit

def facing(normals: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """(P, N) cosines max(0, N . d) between shading normals and texel directions (float32)."""
    out = normals.astype(np.float32) @ directions.astype(np.float32).T
    return np.maximum(out, 0.0, out=out)


def lobe_cosines(normals: np.ndarray, views: np.ndarray, directions: np.ndarray, model: str) -> np.ndarray:
    """(P, N) float32 cosine the specular lobe raises to the power n: N.H (blinn-phong) or R.d
    (phong, phong-classic; R the mirror of the view direction). Not clipped: may be negative."""
    if model == "blinn-phong":
        # N.H without forming H: |v + d|^2 = 2 + 2 v.d
        vd = views.astype(np.float32) @ directions.astype(np.float32).T
        nv = np.einsum("pk,pk->p", normals, views).astype(np.float32)[:, None]
        with np.errstate(invalid="ignore", divide="ignore"):
            return (nv + normals.astype(np.float32) @ directions.astype(np.float32).T) / np.sqrt(
                np.maximum(2.0 + 2.0 * vd, 1e-12))
    if model in ("phong", "phong-classic"):
        r = 2.0 * np.einsum("pk,pk->p", normals, views)[:, None] * normals - views  # mirror of v
        return r.astype(np.float32) @ directions.astype(np.float32).T
    raise ValueError(f"no specular lobe for model {model!r}")


def lobe_norm(shininess: float, model: str) -> tuple[float, float]:
    """The lobe's normalisation factor and its derivative with respect to n."""
    if model == "blinn-phong":
        return (shininess + 8) / (8 * np.pi), 1 / (8 * np.pi)
    if model == "phong":
        return (shininess + 2) / (2 * np.pi), 1 / (2 * np.pi)
    return 1.0, 0.0


def specular_factors(V: np.ndarray, normals: np.ndarray, views: np.ndarray, cube: CubeMap, model: str,
                     texels: np.ndarray | slice = slice(None)) -> tuple[np.ndarray, np.ndarray]:
    """The parts of the specular transport that do not depend on n, for some texels.

    S_ij = A_ij * lobe_norm(n) * c_ij^n, with A = V w max(0, N.d) (phong-classic: V w, the
    paper's term has no cosine) and c = max(0, lobe_cosines); A is 0 wherever c or N.d is 0.

    Returns (A, c): two (P, K) float32 arrays, K = the selected texels.
    """
    dirs = cube.directions[texels]
    cos = facing(normals, dirs)
    c = np.maximum(lobe_cosines(normals, views, dirs, model), 0.0)
    c = np.nan_to_num(c, nan=0.0)
    w = cube.solid_angles[texels].astype(np.float32)[None, :]
    A = V * ((cos > 0) * w if model == "phong-classic" else cos * w)
    A[c <= 0] = 0.0
    return A.astype(np.float32, copy=False), c


def transport(V: np.ndarray, normals: np.ndarray, views: np.ndarray, cube: CubeMap,
              material: Material, specular: np.ndarray | None = None,
              footprint: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray | None]:
    """Transport blocks for a set of pixels: the light texels' contributions per unit radiance.

    The radiance of a texel is constant over it (that is what a texel value means), so its
    diffuse contribution is V x the integral over the texel of max(0, N.d) / pi. That integral is
    N . m_i with m_i the texel's vector solid angle (`CubeMap.vector_solid_angles`), exact for
    texels wholly above the shading horizon and clamped at 0 for the few that straddle it: as
    cheap as a texel-centre rule and exact where the centre rule is off by O(1/R^2). The specular
    lobe is evaluated at the texel centre (w_i max(0, N.d_i) f(d_i), `specular_factors`). Visibility is per texel (V
    may be a supersampled fraction).

    Parameters
    ----------
    V : (P, N) float32 visibility in [0, 1].
    normals, views : (P, 3) shading normals and unit directions to the camera.
    cube : the texel layout.
    specular : (P,) 1 where the pixel's surface has the material's specular term, 0 where it is
        Lambertian (a matte part of a scene whose other parts are glossy: no lobe, and under `plastic`
        no coating: plain D), else the factor on its ks (its part's specular weight); None: every
        pixel has it at weight 1.
    footprint : (P, 2) the roughness^2 each pixel's footprint adds to a microfacet lobe
        (`microfacet.samples_footprint`), or None.

    Returns
    -------
    D : (P, N) float32 diffuse transport for kd = 1;
    S : (P, N) float32 specular transport for ks = 1, or None for a Lambertian material.
    """
    D = diffuse_transport(V, normals, cube, material, views)
    if not material.specular:
        return D, None
    S = specular_transport(V, normals, views, cube, material, footprint=footprint)
    if specular is not None:
        matte_rows(D, S, V, normals, cube, material, specular)
    return D, S


def matte_rows(D: np.ndarray | None, S: np.ndarray | None, V: np.ndarray, normals: np.ndarray, cube: CubeMap,
               material: Material, specular: np.ndarray, texels: np.ndarray | None = None) -> None:
    """In place: the rows of pixels without the specular term (`specular` (P,) 0) lose the lobe (S
    rows 0) and, under `plastic`, the coating (D rows the plain Lambertian ones); the other rows' lobe
    is multiplied by their weight (a part's specular weight, `parts.PixelAlbedo.ks_scales`). `texels`:
    D, S and V hold these texels' columns alone."""
    w = np.asarray(specular)
    if S is not None:
        scaled = np.flatnonzero((w != 0) & (w != 1))
        if len(scaled):
            S[scaled] *= w[scaled, None].astype(S.dtype)
    matte = np.flatnonzero(w == 0)
    if not len(matte):
        return
    if S is not None:
        S[matte] = 0.0
    if D is not None and material.model == PLASTIC:
        D[matte] = diffuse_transport(V[matte], normals[matte], cube, None, texels=texels)


# `lambert_radiance` from this face resolution up: dropping the clamp at a texel straddling the horizon
# changes a pixel's diffuse radiance by less than float32 rounding does (relative RMS over spot_overcast's
# pixels, float64 sums: 1.5e-8 at R = 32, 2.3e-7 at 16, 3.1e-6 at 8; float32 rounding 3.7e-8)
LINEAR_DIFFUSE_RESOLUTION = 32


def linear_diffuse(vis: VisibilityData) -> bool:
    """Whether `lambert_radiance` gives `vis`'s diffuse radiance (see LINEAR_DIFFUSE_RESOLUTION)."""
    return vis.castable_only and vis.cube.resolution >= LINEAR_DIFFUSE_RESOLUTION


def lambert_weights(cube: CubeMap, light: np.ndarray) -> np.ndarray:
    """(N, 3 C) float32 m_i L_i / pi for `lambert_radiance` (light (N, C))."""
    L = np.asarray(light, np.float64)
    L = L[:, None] if L.ndim == 1 else L
    m = cube.vector_solid_angles.astype(np.float64)
    return (m[:, :, None] * L[:, None, :] / np.pi).reshape(len(m), -1).astype(np.float32)


def lambert_radiance(V: np.ndarray, normals: np.ndarray, cube: CubeMap, light: np.ndarray,
                     weights: np.ndarray | None = None) -> np.ndarray:
    """(P, C) float64 the diffuse radiance for kd = 1 under `light` ((N, C) texel radiances):
    sum_i V_i max(0, N . m_i) L_i / pi, which is `diffuse_transport(V, normals, cube) @ light`.

    Summed as N . (V @ (m_i L_i / pi)): one product of V with an (N, 3 C) matrix, without forming
    the (P, N) transport (V is read once: 2.5x faster). The clamp at 0 is dropped, which
    changes nothing where V is 1 but at a few texels: a texel a pixel can see is in front of its
    normal at its centre (`castable`), so N . m_i > 0 unless the texel straddles the horizon with
    most of it below, and there N . m_i is a sliver of the texel's solid angle, below float32
    rounding from R = 32 (LINEAR_DIFFUSE_RESOLUTION; `linear_diffuse` says when to use this). V:
    (P, N) float32 (or 0/1 uint8), 0 wherever a texel is not castable (`VisibilityData.castable_only`:
    where V is 1 behind the normal this sum is wrong); `weights`: `lambert_weights(cube, light)`,
    when the caller has them."""
    W = lambert_weights(cube, light) if weights is None else weights
    C = W.shape[1] // 3
    Y = (np.asarray(V, np.float32) @ W).reshape(len(V), 3, C)
    return np.einsum("pk,pkc->pc", np.asarray(normals, np.float64), Y)


def diffuse_transport(V: np.ndarray, normals: np.ndarray, cube: CubeMap, material: Material | None = None,
                      views: np.ndarray | None = None, out: np.ndarray | None = None,
                      texels: np.ndarray | None = None) -> np.ndarray:
    """(P, N) float32 the diffuse part of `transport` (kd = 1): V max(0, N . m_i) / pi, and for a
    `plastic` material that seen through its coating: x t(N.d_i) t(N.v) / (eta^2 (1 - Fdr)) (t at the
    texel's centre direction; `views` needed).

    V may be float32 (fractions) or the 0/1 uint8 of bit-packed rows (`VisibilityData.blocks(raw=True)`).
    Formed in place (in `out` when given: (P, N) float32), in blocks of rows on both cores. `texels`:
    the columns of these texels alone (V (P, K) holds theirs)."""
    pick = slice(None) if texels is None else texels
    m = cube.vector_solid_angles[pick].astype(np.float32)
    P, N = len(normals), len(m)
    nrm = np.asarray(normals, np.float32)
    out = np.empty((P, N), np.float32) if out is None else out
    inv_pi = np.float32(1.0 / np.pi)
    plastic = material is not None and material.model == PLASTIC
    if plastic:
        coat = mf.coating(material.roughness, material.ior, material.distribution)
        d = cube.directions[pick].astype(np.float32)
        t_view = (coat.transmittance(np.einsum("pk,pk->p", normals, views)) * coat.base_scale).astype(np.float32)

    def run(starts):
        cs = np.empty((KERNEL_ROWS, N), np.float32) if plastic else None
        for a in starts:
            sl = slice(a, min(P, a + KERNEL_ROWS))
            o = out[sl]
            np.matmul(nrm[sl], m.T, out=o)
            np.maximum(o, 0.0, out=o)
            o *= V[sl]
            o *= inv_pi
            if plastic:
                c = cs[: sl.stop - sl.start]
                np.matmul(nrm[sl], d.T, out=c)
                o *= coat.transmittance_f32(c, out=c)
                o *= t_view[sl, None]

    parallel_blocks(run, list(range(0, P, KERNEL_ROWS)))
    return out


def plastic_specular_transport(V: np.ndarray, normals: np.ndarray, views: np.ndarray, cube: CubeMap,
                               material: Material, out: np.ndarray | None = None,
                               footprint: np.ndarray | None = None, texels: np.ndarray | None = None) -> np.ndarray:
    """(P, N) float32 the coating's lobe (ks = 1): V w_i F(v.h) D(h) G1(v) G1(d_i) / (4 N.v) at the texel
    centres, with the roughness widened by the texel and by the pixel's footprint (`footprint`: (P, 2)
    or None; `microfacet.lobe_factors`, `lobe_values`), views with
    N.v < GRAZING_NV capped at the coating's specular albedo (`microfacet.grazing_cap`); blocks of
    rows on both cores (in `out` when given: (P, N) float32). `texels`: the columns of these texels
    alone (V (P, K) holds theirs): a grazing view's cap is still that of its lobe over every texel."""
    P = len(normals)
    d_all = cube.directions.astype(np.float32)
    w_all = cube.solid_angles.astype(np.float32)[None, :]
    d, w = (d_all, w_all) if texels is None else (d_all[texels], w_all[:, texels])
    N = len(d)
    nrm = np.asarray(normals, np.float32)
    vw = np.asarray(views, np.float32)
    nv_all = np.einsum("pk,pk->p", nrm, vw)
    alpha, dist, eta = float(material.roughness), material.distribution, float(material.ior)
    g1v_all = mf.smith_g1((1.0 - np.minimum(nv_all, 1.0) ** 2) / np.maximum(nv_all, 1e-6) ** 2, alpha,
                          dist).astype(np.float32)
    out = np.empty((P, N), np.float32) if out is None else out
    b = min(KERNEL_ROWS, max(P, 1))

    def lobe(rows, dirs, weights, o, nd, vd):
        """The lobe (before the grazing cap and shadowing) of pixels `rows` at `dirs`, in `o`."""
        np.matmul(nrm[rows], dirs.T, out=nd)
        np.matmul(vw[rows], dirs.T, out=vd)
        A, x2, y2, wx, wy, t2d = mf.lobe_factors_f32(nd, nv_all[rows, None].astype(np.float32), vd, weights, eta,
                                                     footprint=None if footprint is None else footprint[rows])
        mf.lobe_values(x2, y2, wx, wy, alpha, dist, out=o)
        o *= A
        o *= mf.smith_g1_f32(t2d, alpha, dist)
        o *= g1v_all[rows, None]
        return o

    def run(blocks):
        nd, vd = np.empty((b, N), np.float32), np.empty((b, N), np.float32)
        for a in blocks:
            sl = slice(a, min(P, a + b))
            k = sl.stop - sl.start
            o = lobe(sl, d, w, out[sl], nd[:k], vd[:k])
            graze = nv_all[sl] < mf.GRAZING_NV
            if graze.any():  # the lobe's energy at grazing views, before shadowing (`microfacet.grazing_cap`)
                rows = np.arange(sl.start, sl.stop)[graze]
                if texels is None:
                    total = o[graze].sum(axis=1)
                else:  # (its sum over every texel: these few rows' whole lobe)
                    g = len(rows)
                    total = lobe(rows, d_all, w_all, np.empty((g, len(d_all)), np.float32),
                                 np.empty((g, len(d_all)), np.float32), np.empty((g, len(d_all)), np.float32)).sum(axis=1)
                o[graze] *= mf.grazing_cap(total, nv_all[rows], alpha, eta, dist).astype(np.float32)[:, None]
            o *= V[sl]

    parallel_blocks(run, list(range(0, P, b)))
    return out


def specular_transport(V: np.ndarray, normals: np.ndarray, views: np.ndarray, cube: CubeMap,
                       material: Material, out: np.ndarray | None = None,
                       footprint: np.ndarray | None = None, texels: np.ndarray | None = None) -> np.ndarray:
    """(P, N) float32 the specular part of `transport` (ks = 1) for the material's model and n:
    V w_i max(0, N.d_i) norm(n) c_i^n with c the lobe cosine, 0 where c <= 0 (`specular_factors`).

    Computed in blocks of rows with reused scratch arrays and c^n = exp(n log c): the same numbers
    as `specular_factors` to float32 rounding, several times faster (no (P, N) temporaries; numpy's
    float32 power is not vectorised, exp and log are). In `out` when given ((P, N) float32). `texels`:
    the columns of these texels alone (V (P, K) holds theirs)."""
    if material.model == PLASTIC:
        return plastic_specular_transport(V, normals, views, cube, material, out, footprint, texels)
    P = len(normals)
    model = material.model
    if model not in ("blinn-phong", "phong", "phong-classic"):
        raise ValueError(f"no specular lobe for model {model!r}")
    norm, _ = lobe_norm(material.shininess, model)
    n = np.float32(material.shininess)
    pick = slice(None) if texels is None else texels
    d = cube.directions[pick].astype(np.float32)
    w = cube.solid_angles[pick].astype(np.float32)[None, :] * np.float32(norm)
    N = len(d)
    out = np.empty((P, N), np.float32) if out is None else out
    nrm = np.asarray(normals, np.float32)
    vw = np.asarray(views, np.float32)
    b = min(KERNEL_ROWS, max(P, 1))

    def run(blocks):
        cos, c, up = np.empty((b, N), np.float32), np.empty((b, N), np.float32), np.empty((b, N), bool)
        for a in blocks:
            sl = slice(a, min(P, a + b))
            k = sl.stop - sl.start
            cs, cc, o, u = cos[:k], c[:k], out[sl], up[:k]
            np.matmul(nrm[sl], d.T, out=cs)  # N.d
            nv = np.einsum("pk,pk->p", nrm[sl], vw[sl])[:, None]
            if model == "blinn-phong":  # N.H = (N.v + N.d) / |v + d|, |v + d|^2 = 2 + 2 v.d
                np.matmul(vw[sl], d.T, out=cc)
                cc *= 2.0
                cc += 2.0
                np.maximum(cc, np.float32(1e-12), out=cc)
                np.sqrt(cc, out=cc)
                np.divide(cs + nv, cc, out=cc)
            else:
                np.matmul(2.0 * nv * nrm[sl] - vw[sl], d.T, out=cc)  # R.d, R the mirror of v
            np.greater(cc, 0.0, out=u)  # (False for NaN)
            np.clip(cc, np.float32(1e-30), np.float32(1.0), out=cc)
            np.log(cc, out=cc)
            cc *= n
            np.exp(cc, out=cc)
            if model == "phong-classic":
                np.greater(cs, 0.0, out=o)
            else:
                np.maximum(cs, 0.0, out=o)
            o *= cc
            o *= w
            o *= V[sl]
            o *= u
    parallel_blocks(run, list(range(0, P, b)))
    return out


def render(vis: VisibilityData, light: np.ndarray, material: Material, rows: int = 512,
           albedo: np.ndarray | None = None, specular: np.ndarray | None = None) -> np.ndarray:
    """Radiance of every used pixel under `light` ((N,) or (N, 3) texel radiances) -> (P, 3).

    `albedo`: (P, 3) a per-pixel relative albedo (several parts, textures: `model.parts`) that
    multiplies the material's kd pixel by pixel; None: kd alone, uniform. `specular`: (P,) 0 for the
    pixels of matte parts (no lobe, no coating: `transport`), else each pixel's factor on ks (its
    part's specular weight); None: the material's term everywhere."""
    L = np.asarray(light, dtype=np.float64)
    if L.ndim == 1:
        L = np.repeat(L[:, None], 3, axis=1)
    if L.shape != (vis.cube.n_texels, 3):
        raise ValueError(f"light must have shape ({vis.cube.n_texels}, 3), got {np.shape(light)}")
    kd = np.asarray(material.kd)
    ks = np.asarray(material.ks)
    P = vis.n_pixels
    out = np.zeros((P, 3))
    Lf = L.astype(np.float32)
    s = vis.samples
    # an even number of equal blocks of at most `rows`: both cores get the same share (a few pixels,
    # under 64 a block, go in one)
    asked = max(1, rows)
    rows = max(1, -(-P // (2 * max(1, -(-P // (2 * asked))))))
    if rows < min(64, asked):
        rows = asked

    # (the diffuse part without its transport, `lambert_radiance`, where V holds only castable texels;
    # not under plastic: its coating's transmittance is not linear in N)
    weights = lambert_weights(vis.cube, L) if linear_diffuse(vis) and material.model != PLASTIC else None
    # the texels the light leaves dark add nothing: for a sparse light (a few points, a sun) the
    # transports are formed for the lit ones alone (a grazing view's cap under plastic is still that
    # of its whole lobe: `plastic_specular_transport`); a wavelet light lights most texels, where
    # gathering their columns of V costs what it saves
    lit = np.flatnonzero(np.any(Lf != 0, axis=1))
    lit = None if len(lit) > SPARSE_LIGHT_SHARE * len(Lf) else lit
    Ll = Lf if lit is None else Lf[lit]

    def run(starts):  # a block of rows on each core, decoded, formed and multiplied there
        for a in starts:
            sl = slice(a, min(P, a + rows))
            fp = mf.samples_footprint(s, sl, material)
            if weights is not None:
                V = vis.block(sl)
                diffuse = lambert_radiance(V, s.normal[sl], vis.cube, L, weights)
                D, V = None, (V if lit is None or not material.specular else V[:, lit])
            else:
                V = vis.block(sl, raw=True)
                V = V if lit is None else V[:, lit]
                D = diffuse_transport(V, s.normal[sl], vis.cube, material, s.view[sl], texels=lit)
            S = specular_transport(V, s.normal[sl], s.view[sl], vis.cube, material, footprint=fp,
                                   texels=lit) if material.specular else None
            if specular is not None and S is not None:
                matte_rows(D, S, V, s.normal[sl], vis.cube, material, specular[sl], lit)
            if D is not None:
                diffuse = D @ Ll
            out[sl] = (kd if albedo is None else kd * albedo[sl]) * diffuse
            if S is not None:
                out[sl] += ks * (S @ Ll)
            D = S = V = None  # (a block's transport goes before the next one's is built: memory)

    parallel_blocks(run, list(range(0, P, rows)))
    return out


def pixels_to_image(values: np.ndarray, pixels: np.ndarray, height: int, width: int,
                    background: float | np.ndarray = 0.0) -> np.ndarray:
    """Scatter per-pixel values ((P,) or (P, C)) into an (H, W[, C]) image."""
    values = np.asarray(values)
    img = np.empty((height, width) + values.shape[1:], dtype=np.float32)
    img[...] = background
    img[pixels[:, 0], pixels[:, 1]] = values
    return img
