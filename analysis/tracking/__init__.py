"""Trajectories, velocities and structure across the shots of a run (no service imports).

A run is a movie: :mod:`.linking` links each shot's particles to the trajectories so far (the
cluster's turn and drift predicted, each particle's depth weighed by how well its table row
knows it, missed shots bridged), :mod:`.trajectories` gives a run's linked table in trackpy's
conventions (``frame, t, particle, x, y, X, Y, Z, vX, vY, vZ``; the ``"trackpy"`` engine links
with ``trackpy.link`` instead), :mod:`.run` goes from exposures to that table in one call,
:mod:`.summary` describes each shot (count, drift, rotation, RMS velocity and kinetic
temperature with the position noise taken out (:mod:`.temperature`), g(r) and a ball's shells
(:mod:`.structure`)).

Helpers: :mod:`.assignment` (gated one-to-one links), :mod:`.motion` (rigid motion),
:mod:`.uncertainty` (depth errors from the table's own columns), :mod:`.units` (particle mass,
eV).
"""
