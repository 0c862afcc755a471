"""plenodust's analysis: from a Lytro F01 exposure to the 3D positions of dust particles.

A library a scientist can use from a notebook; it imports neither ``service`` nor ``driver``.
The subpackages follow the data's way::

    formats      camera files in and out (LFP, RAW + TXT, white images, particle tables)
    camera       the shared geometry: lattice, thin lens, output grid, physical coordinates
    calibration  white image -> fitted lattice and devignetting map (cached per camera)
    lightfield   look-up table -> refocus stack, sub-aperture image
    detection    product stack -> brightness curves and their peaks (candidates)
    depth        candidates -> forward-model fit to the raw pixels, deblending, priors
    pipeline     all of the above as process(exposure, calibration, params) -> Result
    simulation   a simulated camera with known truth, and scoring against it

``errors`` holds the exceptions a user can cause; ``cache`` the one cache a caller owns.
"""
