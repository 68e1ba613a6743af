"""Studies of eofnn's controllers in other simulators' loops, and their reports (``docs/interop.md``): the floor above
the command line (``docs/design.md``, "Floors"); the adapters they drive live in :mod:`eofnn.interop`.

- :mod:`eofnn.studies.study`: record -> identify -> fit closed-loop EOF -> replay -> run in the simulator's loop
  against its best-gain integrator (and the split controller);
- :mod:`eofnn.studies.antialias`: the anti-aliasing EOF learned from the simulator's truth, and the oracle, beside
  the classical controllers of :mod:`eofnn.studies.loop_scans` (the modal integrator, an LQG and predictive Fourier
  control, :mod:`eofnn.studies.pfc`) from the loop's telemetry; :mod:`eofnn.studies.antialias_report` its ratios,
  each predictor's share of the oracle's gain (eta) and ``results.md``;
- :mod:`eofnn.studies.transfer`: the same EOF trained in eofnn's own twin of the system and carried into the loop;
- :mod:`eofnn.studies.sh_system`, :mod:`eofnn.studies.sh_compare`, :mod:`eofnn.studies.sh_diagnostics`: eofnn's
  Shack-Hartmann loop against OOPAO's on one system;
- :mod:`eofnn.studies.report`: error budgets, the small outputs and the shared options of the interop examples.
"""
