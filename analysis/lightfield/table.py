"""The look-up table (the paper's LOT): lens and aperture coordinate of each used green pixel.

For every green sensor pixel inside a micro-image disk the table holds the lens that pixel sits
behind, that lens's position on the micro-lens-array plane ``(s, t)`` and the main-lens aperture
point ``(u, v)`` the pixel sees (docs/camera-model.md, "How a ray reaches the sensor", read
backwards). It is built once per calibration, in a second or two, and cached beside it
(:func:`save_table`, :func:`load_table`).

Weights: each sample carries ``weight``, the response it would have to a scene of unit radiance.
From a calibration this is the normalised white image at that pixel, which already holds the
main lens's ``cos^4`` fall-off and the micro-lens vignetting; without a white image it is
``cos^4`` of the ray angle from the thin-lens geometry. :mod:`analysis.lightfield.refocus` divides summed
light by summed weight, so ``cos^4`` is counted exactly once either way.
"""

from __future__ import annotations

import math
import uuid
import zipfile
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from analysis.formats.atomic_write import atomic_path
from analysis.formats.mapped_npz import map_members, save_aligned
from analysis.camera.model import CameraModel
from analysis.errors import CalibrationError, ParameterError
from analysis.camera.image_grid import ImageGrid

if TYPE_CHECKING:
    from analysis.cache import Cache

# Bump when the saved layout changes, so stale caches are rebuilt, not misread.
# 7: members aligned for memory mapping (analysis.formats.mapped_npz).
# 8: built on the lattice fitted without the micro-images a second stop cuts (calibration cache v3).
#    A table's file is named by its white image, not its lattice; since then
#    analysis.pipeline.tables.get_table also rebuilds a table whose samples disagree with the lattice.
TABLE_FORMAT_VERSION = 8

# Empty lens sites kept around the lattice so that shifted samples near the edge still land
# on the site grid (the simulated f/2 camera shifts by up to about 4 lenses over 0.987 ... 1.013).
_SITE_PAD = 5

# Rows of the sensor handled per step while building, to bound memory.
_BUILD_ROWS = 256


@dataclass(frozen=True, eq=False)
class LightFieldTable:
    """Look-up table from green sensor pixels to lens ``(s, t)`` and aperture ``(u, v)``.

    Samples (one per used green pixel, ordered by lens row ``j``, then lens ``i``):

    Attributes
    ----------
    width, height : int
        Sensor size the table was built for (pixels).
    pixel_index : ndarray of shape (N,), int32
        Flat sensor index ``row * width + col`` of each sample.
    lens : ndarray of shape (N,), int32
        Index of each sample's lens into the ``lens_*`` arrays; non-decreasing (lenses are
        numbered by row ``j``, then ``i``, and samples follow them), so the samples of lens ``k``
        are ``lens_start[k] ... lens_start[k + 1]``.
    u_m, v_m : ndarray of shape (N,), float32
        Main-lens aperture point seen by each sample, metres from the optical axis (upright frame):
        ``-(offset from the micro-image centre) * optics.aperture_m_per_px``.
    weight : ndarray of shape (N,), float32
        Response of the sample to unit scene radiance (white image, or ``cos^4``), divided by
        its median over the table.
    lens_ij : ndarray of shape (L, 2), int32
        Lattice index ``(i, j)`` of each lens.
    lens_xy_m : ndarray of shape (L, 2), float64
        Physical lens centre ``(s, t)`` on the lens plane, metres from the optical axis.
    basis_m : ndarray of shape (2, 2), float64
        Lens-plane metres per lattice step: lens ``(i, j)`` sits at ``basis_m @ (i, j)``.
    aperture_radius_m : float
        Radius of the main-lens aperture ``D / 2`` in metres (the largest ``|(u, v)|``).
    micro_image_radius_px, rim_px : float
        Micro-image radius and the rim width left out (crosstalk), in sensor pixels.
    black_level : float
        Raw black level of the sensor (green channel).
    grid : ImageGrid
        Default output grid of refocused images: covers every lens, one pixel per lens row spacing.
    uid : str
        Identity of this table (made when it is built, kept by :func:`save_table`): what derived
        data is filed under in an :class:`analysis.cache.Cache`.
    """

    width: int
    height: int
    pixel_index: np.ndarray
    lens: np.ndarray
    u_m: np.ndarray
    v_m: np.ndarray
    weight: np.ndarray
    lens_ij: np.ndarray
    lens_xy_m: np.ndarray
    basis_m: np.ndarray
    aperture_radius_m: float
    micro_image_radius_px: float
    rim_px: float
    black_level: float
    grid: ImageGrid
    uid: str = field(default_factory=lambda: uuid.uuid4().hex)

    @property
    def nbytes(self) -> int:
        """Memory held by the table's arrays."""
        return sum(int(getattr(self, name).nbytes) for name in _SAVED_ARRAYS)

    @property
    def n_samples(self) -> int:
        return int(self.pixel_index.size)

    @property
    def n_lenses(self) -> int:
        return int(self.lens_ij.shape[0])

    # --- the lens-site grid the refocus kernels splat onto -------------------------------------
    # Lens (i, j) is site row ``jj = j - j0`` and column ``ii + jj // 2 + col_offset`` with
    # ``ii = i - i0``: each hexagonal row is shifted back by half a lens per row, so the grid is
    # a rectangle about as wide as a lens row instead of a parallelogram (a third less memory).

    @cached_property
    def site_origin(self) -> tuple[int, int]:
        """Lattice index ``(i0, j0)`` of relative site coordinates ``(0, 0)`` (``j0`` includes padding)."""
        return (int(self.lens_ij[:, 0].min()) - _SITE_PAD, int(self.lens_ij[:, 1].min()) - _SITE_PAD)

    @cached_property
    def _site_columns(self) -> tuple[int, int]:
        i0, j0 = self.site_origin
        cols = (self.lens_ij[:, 0] - i0) + (self.lens_ij[:, 1] - j0) // 2
        offset = _SITE_PAD - int(cols.min())
        return offset, int(cols.max()) + offset + 2 + _SITE_PAD

    @property
    def site_col_offset(self) -> int:
        """Added to ``ii + jj // 2`` to give a site's column (see the comment above)."""
        return self._site_columns[0]

    @cached_property
    def site_shape(self) -> tuple[int, int]:
        """``(n_rows, n_cols)`` of the dense lens-site grid (padded)."""
        _, j0 = self.site_origin
        return (int(self.lens_ij[:, 1].max()) - j0 + 1 + _SITE_PAD, self._site_columns[1])

    @cached_property
    def lens_site(self) -> np.ndarray:
        """ndarray (L, 2) float32: each lens's relative lattice index ``(ii, jj)`` (``jj`` = site row)."""
        i0, j0 = self.site_origin
        return np.stack([self.lens_ij[:, 0] - i0, self.lens_ij[:, 1] - j0], axis=1).astype(np.float32)

    @cached_property
    def lens_start(self) -> np.ndarray:
        """ndarray (L + 1,) int64: the samples of lens ``k`` are ``lens_start[k] ... lens_start[k + 1]``."""
        return np.concatenate([[0], np.cumsum(np.bincount(self.lens, minlength=self.n_lenses))]).astype(np.int64)

    def samples_of(self, lenses: np.ndarray) -> np.ndarray:
        """ndarray int64: the sample ids of ``lenses``, lens after lens (each lens's samples are
        consecutive, :attr:`lens_start`)."""
        start = self.lens_start[lenses]
        counts = self.lens_start[lenses + 1] - start
        return np.repeat(start - np.cumsum(np.r_[0, counts[:-1]]), counts) + np.arange(int(counts.sum()))

    @cached_property
    def max_row_shift(self) -> float:
        """Largest ``|row shift|`` of any sample on the site grid per unit of ``1/alpha - 1``."""
        inv = self.inverse_basis_m
        dv = inv[1, 0] * self.u_m.astype(np.float64) + inv[1, 1] * self.v_m.astype(np.float64)
        return float(np.abs(dv).max()) if dv.size else 0.0

    @cached_property
    def max_abs_v_m(self) -> float:
        """Largest ``|v|`` of any sample (metres)."""
        return float(np.abs(self.v_m).max()) if self.v_m.size else 0.0

    @cached_property
    def inverse_basis_m(self) -> np.ndarray:
        """ndarray (2, 2): lattice steps per lens-plane metre (inverse of `basis_m`)."""
        return np.linalg.inv(self.basis_m)

    def lattice_coordinates(self, sx_m: np.ndarray, sy_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Continuous lattice index ``(i, j)`` of lens-plane points (metres)."""
        inv = self.inverse_basis_m
        sx_m = np.asarray(sx_m, dtype=np.float64)
        sy_m = np.asarray(sy_m, dtype=np.float64)
        return inv[0, 0] * sx_m + inv[0, 1] * sy_m, inv[1, 0] * sx_m + inv[1, 1] * sy_m


def build_table(calibration: Any, *, model: CameraModel | None = None, rim_px: float = 1.0,
                min_weight: float = 0.05, grid_oversample: float = 1.0,
                defects: np.ndarray | None = None) -> LightFieldTable:
    """Build the look-up table of a calibration (its fitted lattice, its white image, and the camera's
    defective pixels, which the table leaves out).

    Parameters
    ----------
    calibration : analysis.calibration.calibrate.Calibration
        Has ``.model`` (:class:`CameraModel` with the fitted lattice), ``.devignetting``
        (float32 (H, W), the white image scaled to 0 ... 1) and ``.defect_mask`` (bool (H, W) or
        None: the camera's hot, stuck and dead pixels).
    model : CameraModel, optional
        The exposure's model, when its optics (exit pupil, aperture) differ from the white
        image's; its lattice is replaced by the calibration's fitted one.
    rim_px, min_weight, grid_oversample
        As in :func:`build_table_from_model`.
    defects : ndarray of shape (H, W), bool, optional
        Pixels to leave out instead of the calibration's ``defect_mask``.

    Returns
    -------
    LightFieldTable
    """
    fitted = calibration.model if model is None else model.with_lattice(calibration.model.lattice)
    if defects is None:
        defects = getattr(calibration, "defect_mask", None)
    return build_table_from_model(fitted, calibration.devignetting, rim_px=rim_px, min_weight=min_weight,
                                  grid_oversample=grid_oversample, defects=defects)


def build_table_from_model(model: CameraModel, devignetting: np.ndarray | None = None, *,
                           rim_px: float = 1.0, min_weight: float = 0.05,
                           grid_oversample: float = 1.0, defects: np.ndarray | None = None) -> LightFieldTable:
    """Build the look-up table from a camera model and, optionally, a normalised white image.

    Parameters
    ----------
    model : CameraModel
        Sensor size, micro-image lattice (fitted, ideally) and optics.
    devignetting : ndarray of shape (H, W), float, optional
        White image scaled to 0 ... 1 (``(white - black) / (white_level - black)``). It becomes
        the samples' weights; pixels below ``min_weight`` are left out (gaps between
        micro-images, dead pixels). Without it the weights are ``cos^4`` of the ray angle
        (thin lens). Either way the weights are then divided by their median, so refocused
        values read as raw DN of a typical pixel.
    rim_px : float
        Pixels farther than ``micro_image_radius_px - rim_px`` from their micro-image centre
        are left out: near the rim, light from the neighbouring lens leaks in (crosstalk).
    min_weight : float
        Smallest white-image value a used pixel may have.
    grid_oversample : float
        Output pixels per lens row spacing of the default grid (1: about one pixel per lens).
    defects : ndarray of shape (H, W), bool, optional
        Pixels to leave out (hot, stuck, dead: ``Calibration.defect_mask``), so that refocusing,
        detection and the depth fit never see them.

    Returns
    -------
    LightFieldTable

    Raises
    ------
    ParameterError
        If ``rim_px`` leaves no pixel of the micro-image, or ``devignetting`` or ``defects`` has the
        wrong shape.
    CalibrationError
        If no green pixel ends up in the table (a lattice that misses the sensor).
    """
    optics = model.optics
    radius = optics.micro_image_radius_px
    keep_radius = radius - rim_px
    if not keep_radius > 0.5:
        raise ParameterError(
            f"rim_px={rim_px} leaves no usable pixel of micro-images of radius {radius:.2f} px; "
            "use a smaller rim_px")
    if devignetting is not None:
        devignetting = np.asarray(devignetting)
        if devignetting.shape != (model.height, model.width):
            raise ParameterError(
                f"devignetting image is {devignetting.shape}, the sensor is {(model.height, model.width)}; "
                "pass the white image of this camera")
    if defects is not None:
        defects = np.asarray(defects, dtype=bool)
        if defects.shape != (model.height, model.width):
            raise ParameterError(f"defect mask is {defects.shape}, the sensor is {(model.height, model.width)}; "
                                 "pass the defect map of this camera")
    k_ap = optics.aperture_m_per_px
    p_exit = optics.exit_pupil_m

    parts: dict[str, list[np.ndarray]] = {"pix": [], "i": [], "j": [], "u": [], "v": [], "w": []}
    for r0 in range(0, model.height, _BUILD_ROWS):
        rows = np.arange(r0, min(r0 + _BUILD_ROWS, model.height))
        # Green sites of the BGGR mosaic: (row + col) odd.
        rr = np.repeat(rows, (model.width + 1) // 2)
        cc = (np.tile(np.arange(0, model.width, 2), rows.size)
              + ((rr + 1) % 2))
        ok = cc < model.width
        rr, cc = rr[ok], cc[ok]
        i, j, dx, dy = model.micro_image_offsets(cc + 0.5, rr + 0.5)
        inside = dx * dx + dy * dy <= keep_radius * keep_radius
        if defects is not None:
            inside &= ~defects[rr, cc]
        rr, cc, i, j, dx, dy = rr[inside], cc[inside], i[inside], j[inside], dx[inside], dy[inside]
        u = -dx * k_ap
        v = -dy * k_ap
        if devignetting is not None:
            w = devignetting[rr, cc]  # its own dtype until the median (exact in float64 then)
            good = w.astype(np.float64) >= min_weight
            rr, cc, i, j, u, v, w = rr[good], cc[good], i[good], j[good], u[good], v[good], w[good]
        elif p_exit is None:
            w = np.ones(rr.size)
        else:
            # cos^4 of the ray from aperture point (u, v) to the lens centre (s, t).
            s, t = model.lens_plane_position_m(i, j)
            w = (p_exit * p_exit / (p_exit * p_exit + (s - u) ** 2 + (t - v) ** 2)) ** 2
        # Kept in the table's own dtypes (the same values as casting at the end): a full-size
        # table's parts in int64 and float64 took twice the memory, 230 MB for the depth fit's.
        parts["pix"].append((rr * model.width + cc).astype(np.int32))
        parts["i"].append(i.astype(np.int32))
        parts["j"].append(j.astype(np.int32))
        parts["u"].append(u.astype(np.float32))
        parts["v"].append(v.astype(np.float32))
        parts["w"].append(w)

    if sum(part.size for part in parts["pix"]) == 0:
        raise CalibrationError("no green pixel lies inside a micro-image; the lattice misses the sensor, "
                               "re-run the calibration")
    li = _joined(parts, "i")
    lj = _joined(parts, "j")
    imin, jmin = int(li.min()), int(lj.min())
    ni = int(li.max()) - imin + 1
    key = (lj.astype(np.int64) - jmin) * ni + (li - imin)
    del li, lj
    # Samples ordered by lens (row j, then i): neighbours in memory are neighbours on the lattice.
    order = np.argsort(key, kind="stable")
    key = key[order]
    # Lens numbers in key order (what np.unique(key, return_inverse=True) gives, without its copies).
    first = np.empty(key.size, dtype=bool)
    first[0] = True
    np.not_equal(key[1:], key[:-1], out=first[1:])
    lens_keys = key[first]
    lens = np.cumsum(first, dtype=np.int32)
    lens -= 1
    del key, first
    lens_ij = np.stack([lens_keys % ni + imin, lens_keys // ni + jmin], axis=1).astype(np.int32)
    sx, sy = model.lens_plane_position_m(lens_ij[:, 0], lens_ij[:, 1])
    lens_xy = np.stack([sx, sy], axis=1).astype(np.float64)

    weight = _joined(parts, "w")[order].astype(np.float64)
    weight /= np.median(weight)
    weight = weight.astype(np.float32)
    pixel_index = _joined(parts, "pix")[order]
    u_m = _joined(parts, "u")[order]
    v_m = _joined(parts, "v")[order]
    basis_m = model.lattice.basis * (optics.pixel_pitch_m / optics.projection_factor)
    grid = default_grid(lens_xy, basis_m, oversample=grid_oversample)
    return LightFieldTable(
        width=model.width, height=model.height,
        pixel_index=pixel_index, lens=lens, u_m=u_m, v_m=v_m, weight=weight,
        lens_ij=lens_ij, lens_xy_m=lens_xy, basis_m=np.asarray(basis_m, dtype=np.float64),
        aperture_radius_m=float(radius * k_ap), micro_image_radius_px=float(radius),
        rim_px=float(rim_px), black_level=float(model.black_level), grid=grid)


def _joined(parts: dict[str, list[np.ndarray]], name: str) -> np.ndarray:
    """The concatenated parts of one column, which are let go."""
    return np.concatenate(parts.pop(name))


def default_grid(lens_xy_m: np.ndarray, basis_m: np.ndarray, *, oversample: float = 1.0) -> ImageGrid:
    """The regular grid covering every lens centre, ``oversample`` pixels per lens row spacing.

    The lens row spacing (``sqrt(3)/2`` pitch) is the finest step at which every output pixel
    still has lens sites around it; finer grids interpolate between them.
    """
    if oversample <= 0:
        raise ParameterError(f"grid_oversample must be positive, got {oversample}")
    row_spacing = float(abs(basis_m[1, 1]))
    step = row_spacing / oversample
    x_lo, y_lo = lens_xy_m.min(axis=0)
    x_hi, y_hi = lens_xy_m.max(axis=0)
    width = int(math.floor((x_hi - x_lo) / step)) + 1
    height = int(math.floor((y_hi - y_lo) / step)) + 1
    # Centre the grid on the lens extent.
    x0 = 0.5 * (x_lo + x_hi) - 0.5 * (width - 1) * step
    y0 = 0.5 * (y_lo + y_hi) - 0.5 * (height - 1) * step
    return ImageGrid(width=width, height=height, x0_m=float(x0), y0_m=float(y0), step_m=step)


_SAVED_ARRAYS = ("pixel_index", "lens", "u_m", "v_m", "weight", "lens_ij", "lens_xy_m", "basis_m")
#: Arrays of a sample each: mapped from the file by :func:`load_table`.
_MAPPED_ARRAYS = ("pixel_index", "lens", "u_m", "v_m", "weight")
_SAVED_SCALARS = ("width", "height", "aperture_radius_m", "micro_image_radius_px", "rim_px", "black_level", "uid")
#: Kind of the cache entries that :func:`save_table` keeps with a table (:mod:`analysis.lightfield.refocus`).
NORMALISATION = "normalisation"


def save_table(table: LightFieldTable, path: str | Path, *, cache: Cache | None = None) -> Path:
    """Write the table to an ``.npz`` file, with the refocus normalisations ``cache`` holds for it.

    The file is written beside its final name and renamed into place, so a reader never sees
    half a table.
    """
    path = Path(path)
    payload: dict[str, np.ndarray] = {name: getattr(table, name) for name in _SAVED_ARRAYS}
    for name in _SAVED_SCALARS:
        payload[name] = np.asarray(getattr(table, name))
    g = table.grid
    payload["grid"] = np.array([g.width, g.height, g.x0_m, g.y0_m, g.step_m], dtype=np.float64)
    payload["format_version"] = np.asarray(TABLE_FORMAT_VERSION)
    saved = [] if cache is None else list(cache.entries(NORMALISATION, table.uid))
    for n, (key, value) in enumerate(saved):
        payload[f"norm{n}_key"] = np.frombuffer(key[2], dtype=np.uint8)
        payload[f"norm{n}_value"] = value
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        save_aligned(fh, payload, release=True)
    return path


def load_table(path: str | Path, *, cache: Cache | None = None) -> LightFieldTable:
    """Read a table written by :func:`save_table`; its refocus normalisations go into ``cache``.

    The per-sample arrays and the normalisations are mapped from the file, not read: an exposure
    reads the normalisations of its own alphas only, and the depth fit's table of a drifted lattice
    gives back the pages of the undrifted one once it has been derived from it
    (:func:`analysis.pipeline.tables.drifted_fit_table`).

    Raises
    ------
    CalibrationError
        If the file is missing, unreadable or of another format version; rebuild the table
        with :func:`build_table`.
    """
    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as data:
            if int(data["format_version"]) != TABLE_FORMAT_VERSION:
                raise CalibrationError(
                    f"look-up table {path} has format {int(data['format_version'])}, this version reads "
                    f"{TABLE_FORMAT_VERSION}; delete it so it is rebuilt from the calibration")
            n_norms = 0
            while f"norm{n_norms}_key" in data.files:
                n_norms += 1
            mapped = map_members(path, [*_MAPPED_ARRAYS, *(f"norm{n}_value" for n in range(n_norms))], mode="c")

            def read(name: str) -> np.ndarray:
                array = mapped.get(name)
                return array if array is not None and array.flags.aligned else data[name]
            arrays = {name: read(name) for name in _SAVED_ARRAYS}
            scalars = {name: data[name].item() for name in _SAVED_SCALARS}
            gw, gh, gx, gy, gs = data["grid"].tolist()
            norms = {data[f"norm{n}_key"].tobytes(): read(f"norm{n}_value") for n in range(n_norms)}
    except (OSError, KeyError, ValueError, zipfile.BadZipFile) as exc:
        raise CalibrationError(f"cannot read look-up table {path} ({exc}); delete it so it is rebuilt "
                               "from the calibration") from exc
    table = LightFieldTable(
        width=int(scalars.pop("width")), height=int(scalars.pop("height")), **arrays, **scalars,
        grid=ImageGrid(width=int(gw), height=int(gh), x0_m=gx, y0_m=gy, step_m=gs))
    if cache is not None:
        for key, value in norms.items():
            cache.put((NORMALISATION, table.uid, key), value)
    return table
