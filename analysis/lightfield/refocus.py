"""Refocus stack, sub-aperture image and their products (the paper's equation 2, Ng 2005).

Shift-only refocus: the ray through aperture point ``u`` recorded at lens centre ``s_k`` is
added at lens-plane position ``s_hat = s_k + u * (1/alpha - 1)``. Every slice then has the
same magnification: a point at ``(X, Y, Z)`` whose image forms at ``Fp`` is sharp at
``alpha = Fp / P`` and lands at ``s_hat = (X, Y) * P / Z`` (metres on the lens plane), which
:class:`ImageGrid` turns into output pixels.

How a slice is formed:

1. Samples (table entries) are read from the raw image, minus the black level and the diffuse
   background (plasma glow, taken to light the sensor like the white image, so it is
   ``level * weight`` with a robust median for the level). Unless ``noise_sigmas=None``, only
   samples above ``noise_sigmas`` robust standard deviations contribute: dust frames are
   sparse, so this skips almost all the work, and the skipped samples are pure noise.
2. Each sample is shifted (continuously, sub-lens) and split, for all alphas at once, either
   bilinearly over the 4 output pixels around it (``method="bilinear"``) or barycentrically
   over the 3 lens sites of the lattice triangle it falls in (``method="triangles"``, the
   issue's wording), whose values are then interpolated barycentrically onto the regular
   :class:`ImageGrid`. The default ``"auto"`` takes bilinear on the default grid and
   coarser ones, triangles on finer ones.
3. Each pixel (or site) is divided by the light it *could* receive: the same splat of every
   sample's ``weight`` (the normalised white image, which holds ``cos^4`` and micro-lens
   vignetting, or ``cos^4`` alone without one). So ``E = sum(b * (raw - black - bg)) /
   sum(b * weight)``: a white scene gives a flat image, lattice and edge patterns cancel, and
   ``cos^4`` is counted once (it is in both the data and the weight; nothing divides by the
   white image per pixel). Weights have median 1, so values read as raw DN of a median-weight
   pixel. Targets that could receive less than ``min_coverage`` of the typical light are 0.

Why bilinear by default: the triangle route smooths twice (a splat tent one lens pitch wide,
then an interpolation tent), which flattens each particle's brightness curve over alpha. On
simulated isolated particles (``bench/accuracy_refocus.py``, default grid) the bilinear splat
finds the brightest slice with an RMS error of 1.0 alpha steps against 1.5, and places the
particle within 0.10 lens pitch RMS against 0.12; it is also faster (no interpolation pass).
Its limit: on a grid finer than the default (one pixel per lens row spacing, 0.87 pitch), at
alphas within about 0.002 of 1 the samples all sit on lens centres and pixels between them get
no light (0, holes); the triangle route has no holes on any grid. A finer grid gains nothing
in accuracy anyway (same script), since the look-up table knows which lens a ray entered, not
where in it: a focused particle is a blob one lens wide.

The normalisation depends only on the table, method, grid and alphas; it is computed once (all
samples, about a second full size) and kept in the caller's :class:`analysis.cache.Cache` (pass
the same one to every call; without one, each call works it out afresh), and
:func:`analysis.lightfield.table.save_table` stores it with the table.
"""

from __future__ import annotations

import numba
import numpy as np

from analysis.cache import Cache
from analysis.lightfield import kernels as kern
from analysis.camera.model import Optics
from analysis.errors import ParameterError
from analysis.camera.image_grid import ImageGrid
from .background import BackgroundMap
from .samples import Samples, select_samples
from .table import NORMALISATION, LightFieldTable

__all__ = ["default_alphas", "alphas_for_depth_range", "refocus_stack", "subaperture_image", "products",
           "normalisation", "prepare_normalisations"]

DEFAULT_MIN_COVERAGE = 0.25
METHODS = ("auto", "bilinear", "triangles")
DEFAULT_METHOD = "auto"
# Normalisations are splatted in bands laid out for shifts of a blur this many lens pitches wide
# (wider than any stack the pipeline refocuses), whatever alphas are computed together.
NORMALISATION_REACH_PITCHES = 16.0
def default_alphas(n: int = 40, lo: float = 0.987, hi: float = 1.013) -> np.ndarray:
    """``n`` refocus parameters evenly spaced over ``[lo, hi]`` (float64, ascending).

    >>> default_alphas(3).round(3).tolist()
    [0.987, 1.0, 1.013]
    """
    if n < 1 or not (0 < lo <= hi):
        raise ParameterError(f"need n >= 1 and 0 < lo <= hi for the alpha range, got n={n}, lo={lo}, hi={hi}")
    return np.linspace(lo, hi, n)


def alphas_for_depth_range(z_min_mm: float, z_max_mm: float, n: int, optics: Optics) -> np.ndarray:
    """``n`` alphas evenly spaced (ascending) between the alphas in focus at two depths.

    Uses the thin-lens model of ``optics`` (``Optics.alpha_of_z``); the near depth gives the
    largest alpha.

    Raises
    ------
    ParameterError
        If the range is empty, not beyond the focal length, or ``n < 1``.
    MetadataError
        If the optics have no exit-pupil distance (use explicit alphas then).
    """
    if n < 1 or not (0 < z_min_mm < z_max_mm):
        raise ParameterError(f"need 0 < z_min_mm < z_max_mm and n >= 1, got {z_min_mm}, {z_max_mm}, n={n}")
    if z_min_mm <= optics.focal_length_m * 1e3:
        raise ParameterError(f"z_min_mm={z_min_mm} is inside the focal length ({optics.focal_length_m * 1e3} mm); "
                             "objects that close are not imaged")
    a_near = float(optics.alpha_of_z(z_min_mm))
    a_far = float(optics.alpha_of_z(z_max_mm))
    return np.linspace(a_far, a_near, n)


def _coeffs(alphas: np.ndarray) -> np.ndarray:
    alphas = np.asarray(alphas, dtype=np.float64).reshape(-1)
    if alphas.size == 0 or not np.all(np.isfinite(alphas)) or np.any(alphas <= 0):
        raise ParameterError("alphas must be a non-empty list of positive numbers (e.g. default_alphas())")
    return (1.0 / alphas - 1.0).astype(np.float32)


def _grid_key(grid: ImageGrid) -> bytes:
    return np.array([grid.width, grid.height, grid.x0_m, grid.y0_m, grid.step_m], dtype=np.float64).tobytes()


def _lens_pixels(table: LightFieldTable, grid: ImageGrid, cache: Cache) -> np.ndarray:
    """Each lens centre's output-grid position ``(col, row)``, float32 (L, 2)."""
    def make() -> np.ndarray:
        col, row = grid.to_pixels(table.lens_xy_m[:, 0], table.lens_xy_m[:, 1])
        return np.stack([col, row], axis=1).astype(np.float32)
    return cache.get_or_make(("refocus", table.uid, "lens_px", _grid_key(grid)), make)


def _targets(table: LightFieldTable, method: str, grid: ImageGrid, cache: Cache) -> tuple[np.ndarray, float, int]:
    """Per-lens target row (site row, or output-grid row), row shift per unit coefficient, and
    the number of target cells of a method."""
    if method == "triangles":
        n_rows, n_cols = table.site_shape
        return table.lens_site[:, 1], table.max_row_shift, n_rows * n_cols
    return _lens_pixels(table, grid, cache)[:, 1], table.max_abs_v_m / grid.step_m, grid.height * grid.width


def _band_starts(table: LightFieldTable, ids: np.ndarray, coeffs: np.ndarray, method: str,
                 grid: ImageGrid, cache: Cache, min_reach_coeff: float = 0.0) -> np.ndarray:
    """Cut samples (ordered by lens row) into bands of lens rows that threads may splat in turn.

    Band ``b`` writes target rows from its lenses' lowest row minus ``reach`` to their highest
    plus ``reach + 1``; bands are made tall enough that bands two apart never meet (see the
    kernels), and about 8 per thread so that clustered particles still share out.
    """
    target_row, shift_per_coeff, _ = _targets(table, method, grid, cache)
    reach = int(np.ceil(shift_per_coeff * max(float(np.abs(coeffs).max()), min_reach_coeff))) + 1
    key = ("refocus", table.uid, "bands", method, _grid_key(grid) if method == "bilinear" else b"", reach,
           numba.get_num_threads())
    edges = cache.get(key)
    if edges is None:
        lens_row = table.lens_site[:, 1].astype(np.int64)
        n_lens_rows = int(lens_row.max()) + 1
        lo = np.full(n_lens_rows, np.inf)
        hi = np.full(n_lens_rows, -np.inf)
        np.minimum.at(lo, lens_row, target_row)
        np.maximum.at(hi, lens_row, target_row)
        lo = np.minimum.accumulate(lo[::-1])[::-1]     # empty rows inherit their neighbours
        hi = np.maximum.accumulate(np.where(np.isfinite(hi), hi, -np.inf))
        lo = np.where(np.isfinite(lo), lo, hi)
        rows = max(2, n_lens_rows // (8 * numba.get_num_threads()))
        while True:
            edges = np.arange(0, n_lens_rows + rows, rows)
            starts = edges[:-1]
            ends = np.minimum(edges[1:], n_lens_rows)
            w_lo = np.array([lo[a:b].min() for a, b in zip(starts, ends)]) - reach
            w_hi = np.array([hi[a:b].max() for a, b in zip(starts, ends)]) + reach + 1
            if w_lo.size < 3 or np.all(w_hi[:-2] < w_lo[2:] - 1):
                break
            rows += 1
        cache.put(key, edges)
    sample_rows = table.lens_site[table.lens[ids], 1] if ids.size else np.zeros(0, np.float32)
    return np.searchsorted(sample_rows, edges.astype(np.float32), side="left").astype(np.int64)


def _refocus_into(table: LightFieldTable, ids: np.ndarray, values: np.ndarray, coeffs: np.ndarray, method: str,
                  grid: ImageGrid, scale: np.ndarray | None, out: np.ndarray, cache: Cache,
                  min_reach_coeff: float = 0.0) -> np.ndarray:
    """Splat samples and write the slices (n_alpha, height, width) into ``out``.

    ``scale`` is the normalisation (see :func:`normalisation`); ``None`` leaves the raw sums,
    in the method's own layout (bilinear: ``out`` itself; triangles: returned site sums).
    """
    bands = _band_starts(table, ids, coeffs, method, grid, cache, min_reach_coeff)
    if method == "bilinear":
        lens_px = _lens_pixels(table, grid, cache)
        kern.splat_bilinear(ids, values, table.lens, lens_px, table.u_m, table.v_m, 1.0 / grid.step_m,
                            coeffs, bands, out)
        if scale is not None:
            for plane, inv in zip(out, scale):  # slice by slice: the normalisation need not be one array
                plane *= inv
        return out
    n_rows, n_cols = table.site_shape
    key = ("refocus", table.uid, "acc", n_rows * n_cols, coeffs.size)
    acc = cache.take(key)                 # taken: a concurrent caller allocates its own
    if acc is None:
        acc = np.empty((n_rows * n_cols, coeffs.size), dtype=np.float32)
    kern.splat(ids, values, table.lens, table.lens_site, table.u_m, table.v_m, table.inverse_basis_m,
               coeffs, n_cols, n_rows, table.site_col_offset, bands, acc)
    if scale is None:
        return acc                        # the caller owns it now
    i0, j0 = table.site_origin
    inv_b = table.inverse_basis_m
    # Relative lattice coordinates of output pixel (0, 0) and per column / row step.
    origin = inv_b @ np.array([grid.x0_m, grid.y0_m]) - np.array([i0, j0], dtype=np.float64)
    d_col = inv_b @ np.array([grid.step_m, 0.0])
    d_row = inv_b @ np.array([0.0, grid.step_m])
    kern.interpolate_to_grid(acc, scale, n_cols, n_rows, table.site_col_offset, origin, d_col, d_row, out)
    cache.put(key, acc)
    return out


def _resolve_method(method: str, table: LightFieldTable, grid: ImageGrid) -> str:
    """``"auto"``: bilinear on grids no finer than one pixel per lens row spacing (where it leaves
    no holes), lens triangles on finer ones."""
    if method not in METHODS:
        raise ParameterError(f"unknown refocus method {method!r}; choose one of {', '.join(METHODS)}")
    if method == "auto":
        return "bilinear" if grid.step_m >= 0.99 * abs(float(table.basis_m[1, 1])) else "triangles"
    return method


def normalisation(table: LightFieldTable, alphas: np.ndarray, *, method: str = DEFAULT_METHOD,
                  grid: ImageGrid | None = None, keep: np.ndarray | None = None, key_extra: bytes = b"",
                  min_coverage: float = DEFAULT_MIN_COVERAGE, cache: Cache | None = None) -> np.ndarray:
    """Inverse of the light each lens site (or output pixel) can receive at each alpha.

    Computed once per table, method, grid and alpha (all samples, about a second full size for 40
    alphas) and kept in ``cache`` slice by slice, so that stacks over overlapping alpha ranges
    share them (:func:`analysis.lightfield.table.save_table` writes them with the table).

    Returns
    -------
    ndarray, float32
        ``1 / sum(b * weight)`` over all samples (or those in ``keep``); 0 where a target could
        receive less than ``min_coverage`` times the median of those that receive any. Shape
        (n_alpha, grid.height, grid.width) for "bilinear", (n_sites, n_alpha) for "triangles".
    """
    grid = table.grid if grid is None else grid
    method = _resolve_method(method, table, grid)
    slices = _normalisation_slices(table, alphas, method, grid, keep, key_extra, min_coverage,
                                   Cache() if cache is None else cache)
    return np.stack(slices, axis=0 if method == "bilinear" else 1)


def _normalisation_slices(table: LightFieldTable, alphas: np.ndarray, method: str, grid: ImageGrid,
                          keep: np.ndarray | None, key_extra: bytes, min_coverage: float,
                          cache: Cache) -> list[np.ndarray]:
    """:func:`normalisation` as the cached slices, one per alpha (not copied into one array)."""
    coeffs = _coeffs(alphas)
    tail = (np.float32(min_coverage).tobytes() + key_extra + method.encode()
            + (_grid_key(grid) if method == "bilinear" else b""))
    keys = [(NORMALISATION, table.uid, c.tobytes() + tail) for c in coeffs]
    slices = [cache.get(key) for key in keys]
    missing = [a for a, got in enumerate(slices) if got is None]
    if missing:
        for a, inv in zip(missing, _inverse_coverage(table, coeffs[missing], method, grid, keep, min_coverage, cache)):
            slices[a] = cache.put(keys[a], inv)
    return slices


def _inverse_coverage(table: LightFieldTable, coeffs: np.ndarray, method: str, grid: ImageGrid,
                      keep: np.ndarray | None, min_coverage: float, cache: Cache) -> list[np.ndarray]:
    """One inverse-coverage slice per coefficient (see :func:`normalisation`)."""
    ids = np.arange(table.n_samples, dtype=np.int32) if keep is None else np.flatnonzero(keep).astype(np.int32)
    # One band layout whatever the alphas computed together, so that a slice's sums run in the same
    # order and come out the same to the last bit, whichever stacks were refocused before.
    pitch = float(np.hypot(*table.basis_m[:, 0]))
    reach = NORMALISATION_REACH_PITCHES * pitch / table.aperture_radius_m
    if method == "bilinear":
        den = np.empty((coeffs.size, grid.height, grid.width), dtype=np.float32)
        _refocus_into(table, ids, table.weight[ids], coeffs, method, grid, None, den, cache, reach)
        per_alpha = list(den)
    else:
        den = _refocus_into(table, ids, table.weight[ids], coeffs, method, grid, None, None, cache, reach)
        per_alpha = list(den.T)
    out = []
    for d in per_alpha:
        inv = np.zeros(d.shape, dtype=np.float32)
        positive = d[d > 0]
        if positive.size:
            enough = d >= min_coverage * float(np.median(positive))
            inv[enough] = 1.0 / d[enough]
        out.append(inv)
    return out


def prepare_normalisations(table: LightFieldTable, alphas: np.ndarray | None = None, *, cache: Cache,
                           fraction: float = 0.3, method: str = DEFAULT_METHOD, grid: ImageGrid | None = None,
                           min_coverage: float = DEFAULT_MIN_COVERAGE) -> None:
    """Compute the normalisations of the stack (``alphas``) and the sub-aperture image (``fraction``)
    into ``cache``.

    About a second full size, once per table and settings; call it before
    :func:`analysis.lightfield.table.save_table` so the saved table carries them and a fresh process
    refocuses at full speed from its first exposure.
    """
    normalisation(table, default_alphas() if alphas is None else alphas, method=method, grid=grid,
                  min_coverage=min_coverage, cache=cache)
    _sub_normalisation(table, fraction, method, table.grid if grid is None else grid, min_coverage, cache)


def _sub_normalisation(table: LightFieldTable, fraction: float, method: str, grid: ImageGrid,
                       min_coverage: float, cache: Cache) -> np.ndarray:
    return normalisation(table, np.ones(1), method=method, grid=grid, keep=_central_samples(table, fraction, cache),
                         key_extra=b"sub" + np.float64(fraction).tobytes(), min_coverage=min_coverage, cache=cache)


def refocus_stack(image: np.ndarray | None, table: LightFieldTable, alphas: np.ndarray | None = None, *,
                  grid: ImageGrid | None = None, method: str = DEFAULT_METHOD, black_level: float | None = None,
                  background: float | BackgroundMap | None = None, noise_sigmas: float | None = 3.0,
                  min_coverage: float = DEFAULT_MIN_COVERAGE, samples: Samples | None = None,
                  out: np.ndarray | None = None, cache: Cache | None = None) -> np.ndarray:
    """Refocused images ``E_alpha`` of one raw exposure, one per alpha.

    Parameters
    ----------
    image : ndarray of shape (H, W), uint16, or None
        Raw sensor counts (the table's sensor size); None when ``samples`` are given (the caller
        may then let a large image go before the stack is made).
    table : LightFieldTable
    alphas : ndarray of shape (A,), optional
        Refocus parameters (virtual image plane at ``alpha * P``); default :func:`default_alphas`.
    grid : ImageGrid, optional
        Output grid; default ``table.grid``.
    method : {"auto", "bilinear", "triangles"}
        ``"bilinear"``: each shifted sample is split over the 4 output pixels around it.
        ``"triangles"``: over the 3 lens sites of its lattice triangle, then the sites are
        interpolated barycentrically onto the grid. ``"auto"``: bilinear unless the grid is
        finer than one pixel per lens row spacing (where bilinear leaves holes near alpha = 1).
        See the module docstring for the choice.
    black_level, background, noise_sigmas
        Sample selection, see :func:`select_samples` (ignored when ``samples`` is given).
    min_coverage : float
        Targets (pixels or lens sites) that could receive less than this fraction of the
        typical light are left out (0).
    samples : Samples, optional
        A selection from :func:`select_samples`, to share it with :func:`subaperture_image`.
    out : ndarray of shape (A, grid.height, grid.width), float32, optional
        Where to write the stack.
    cache : Cache, optional
        Keeps the normalisation and work buffers between calls (see the module docstring).

    Returns
    -------
    ndarray of shape (A, grid.height, grid.width), float32
        Light per unit weight, background subtracted: raw DN that a median-weight pixel would
        read from the scene at that place; 0 where no lens contributes, never NaN.

    Raises
    ------
    ParameterError
        If the image does not match the table, alphas are not positive, or ``out`` is wrong.

    Examples
    --------
    >>> from analysis.camera.model import CameraModel
    >>> from analysis.lightfield.table import build_table_from_model
    >>> from analysis.simulation.camera import simulated_camera_metadata
    >>> table = build_table_from_model(CameraModel.from_metadata(simulated_camera_metadata(size=64)))
    >>> dark = np.full((64, 64), 168, dtype=np.uint16)
    >>> stack = refocus_stack(dark, table, default_alphas(5))
    >>> stack.shape == (5, *table.grid.shape), float(np.abs(stack).max())
    (True, 0.0)
    """
    alphas = default_alphas() if alphas is None else alphas
    coeffs = _coeffs(alphas)
    grid = table.grid if grid is None else grid
    method = _resolve_method(method, table, grid)
    shape = (coeffs.size, grid.height, grid.width)
    if out is None:
        out = np.empty(shape, dtype=np.float32)
    elif out.shape != shape or out.dtype != np.float32 or not out.flags.c_contiguous:
        raise ParameterError(f"out must be a C-contiguous float32 array of shape {shape}")
    samples = _selected(image, table, samples, black_level, background, noise_sigmas)
    cache = Cache() if cache is None else cache
    # The bilinear stack is scaled slice by slice from the cached slices: a stacked copy of
    # them would be one more stack's worth of memory (23 MB full size) at a pass's peak.
    inv = _normalisation_slices(table, alphas, method, grid, None, b"", min_coverage, cache)
    if method != "bilinear":
        inv = np.stack(inv, axis=1)
    return _refocus_into(table, samples.ids, samples.values, coeffs, method, grid, inv, out, cache)


def _selected(image: np.ndarray | None, table: LightFieldTable, samples: Samples | None, black_level: float | None,
              background: float | BackgroundMap | None, noise_sigmas: float | None) -> Samples:
    """``samples``, or those :func:`select_samples` takes from ``image``."""
    if samples is not None:
        return samples
    if image is None:
        raise ParameterError("refocusing needs the raw image or the samples selected from it")
    return select_samples(image, table, black_level=black_level, background=background, noise_sigmas=noise_sigmas)


def subaperture_image(image: np.ndarray | None, table: LightFieldTable, *, fraction: float = 0.3,
                      blur_sigma_px: float = 1.0, grid: ImageGrid | None = None, method: str = DEFAULT_METHOD,
                      black_level: float | None = None, background: float | BackgroundMap | None = None,
                      noise_sigmas: float | None = 3.0, min_coverage: float = DEFAULT_MIN_COVERAGE,
                      samples: Samples | None = None, cache: Cache | None = None) -> np.ndarray:
    """Image through the central ``fraction`` of the aperture (digital stopping-down), blurred.

    Only samples with ``|(u, v)| <= fraction * aperture_radius_m`` contribute, unshifted
    (``alpha = 1``); a small aperture has a large depth of field, so every particle shows, at
    the same magnification as the refocused slices. The result is blurred with a Gaussian of
    ``blur_sigma_px`` output pixels and clipped at 0 (so that a product with a slice never turns
    two negative noise values into a positive one).

    Parameters
    ----------
    image : ndarray of shape (H, W), uint16, or None
        Raw sensor counts; None when ``samples`` are given.
    table : LightFieldTable
    fraction : float
        Radius of the aperture part used, as a fraction of the aperture radius (0, 1].
    blur_sigma_px : float
        Gaussian blur in output pixels (0: none).
    grid, method, black_level, background, noise_sigmas, min_coverage, samples, cache
        As in :func:`refocus_stack`.

    Returns
    -------
    ndarray of shape (grid.height, grid.width), float32, >= 0

    Raises
    ------
    ParameterError
        If ``fraction`` or ``blur_sigma_px`` is out of range, or the image does not match the table.
    """
    if not (0 < fraction <= 1):
        raise ParameterError(f"fraction of the aperture must be in (0, 1], got {fraction}")
    if blur_sigma_px < 0:
        raise ParameterError(f"blur_sigma_px must be >= 0, got {blur_sigma_px}")
    grid = table.grid if grid is None else grid
    samples = _selected(image, table, samples, black_level, background, noise_sigmas)
    method = _resolve_method(method, table, grid)
    cache = Cache() if cache is None else cache
    central = _central_samples(table, fraction, cache)
    inv = _sub_normalisation(table, fraction, method, grid, min_coverage, cache)
    chosen = central[samples.ids]
    out = np.empty((1, grid.height, grid.width), dtype=np.float32)
    img = _refocus_into(table, samples.ids[chosen], samples.values[chosen], _coeffs(np.ones(1)), method, grid,
                        inv, out, cache)[0]
    if blur_sigma_px > 0:
        img = _gaussian_blur(img, blur_sigma_px)
    np.maximum(img, 0.0, out=img)
    return img


def _gaussian_blur(image: np.ndarray, sigma_px: float) -> np.ndarray:
    """Gaussian blur (truncated at 4 sigma, zero outside the image), float32."""
    half = max(1, int(np.ceil(4.0 * sigma_px)))
    x = np.arange(-half, half + 1, dtype=np.float64)
    taps = np.exp(-0.5 * (x / sigma_px) ** 2)
    taps = (taps / taps.sum()).astype(np.float32)
    out = np.empty_like(image)
    kern.gaussian_blur(np.ascontiguousarray(image), taps, out)
    return out


def _central_samples(table: LightFieldTable, fraction: float, cache: Cache) -> np.ndarray:
    """Bool mask of the samples within ``fraction`` of the aperture radius (cached)."""
    def make() -> np.ndarray:
        r_max = np.float32(fraction * table.aperture_radius_m)
        r2 = table.u_m * table.u_m          # float32 temporaries: the mask needs no more
        r2 += table.v_m * table.v_m
        return r2 <= r_max * r_max
    return cache.get_or_make(("refocus", table.uid, "central", float(fraction)), make)


def products(stack: np.ndarray, subaperture: np.ndarray, *, out: np.ndarray | None = None) -> np.ndarray:
    """Each refocused slice times the sub-aperture image (the paper's multiplicative combination).

    Parameters
    ----------
    stack : ndarray of shape (A, H, W), float32
    subaperture : ndarray of shape (H, W), float32
    out : ndarray like ``stack``, optional (may be ``stack`` itself to save memory)

    Returns
    -------
    ndarray of shape (A, H, W), float32
    """
    stack = np.ascontiguousarray(stack, dtype=np.float32)
    subaperture = np.ascontiguousarray(subaperture, dtype=np.float32)
    if stack.ndim != 3 or subaperture.shape != stack.shape[1:]:
        raise ParameterError(f"stack {stack.shape} and sub-aperture image {subaperture.shape} must be "
                             "(A, H, W) and (H, W) on the same grid")
    if out is None:
        out = np.empty_like(stack)
    kern.multiply_slices(stack, subaperture, out)
    return out
