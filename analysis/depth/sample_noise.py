"""How noisy each of the depth fit's devignetted samples is, for weighing them (weighted least squares)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class SampleNoise:
    """One raw sample's noise variance, ``read + shot * signal`` (DN^2; signal in DN: the extended
    light behind the sample times its white weight), as the exposure's samples show it
    (:attr:`analysis.lightfield.samples.Samples.noise`), and the typical background level
    (devignetted DN) at which a full-weight sample counts once.

    The fit's samples are devignetted (divided by their white weight ``w``), so their noise grows as
    ``1 / w``: each counts in proportion to its inverse variance, ``w^2 / (read + shot w level)``.
    Its own light is left out of the variance: weights taken from the observed values favour the
    samples that read low and doubled the depth errors on tuning frames, and weights from the
    coarse pass's model were worse than these (stop 41).
    """

    read: float
    shot: float
    typical_level: float

    def root_weights(self, weight: np.ndarray, level: np.ndarray) -> np.ndarray:
        """Square roots of the samples' weights in the fit, for white weights ``weight`` and the
        background ``level`` behind each (devignetted DN); all 1 without a noise model."""
        typical = self.read + self.shot * max(self.typical_level, 0.0)
        if not typical > 0.0:
            return np.ones(np.shape(weight))
        variance = self.read + self.shot * weight * np.maximum(level, 0.0)
        return weight * np.sqrt(typical / np.maximum(variance, 1e-12 * typical))
