"""eofnn's controllers inside other simulators' closed loops (``docs/interop.md``): the adapters.

- :mod:`eofnn.interop.loop`: the shared part: a simulator adapter protocol, the closed loop with its delay line,
  controllers (integrator with dither, the exported runtime filter, a torch controller), telemetry out;
- :mod:`eofnn.interop.oopao` (needs ``pip install 'eofnn[interop]'``) and :mod:`eofnn.interop.hcipy`: the
  simulators. Neither simulator is imported before an adapter is made: ``import eofnn`` needs neither;
- :mod:`eofnn.interop.pfc`: another simulator's actuator lattice as the square grid predictive Fourier control reads;
- :mod:`eofnn.interop.shift`: the one-line warning when a checkpoint runs in conditions other than its training's.

The studies that drive these adapters (the worked example, the anti-aliasing study, the transfer, the Shack-Hartmann
comparison) and their reports live one floor above the command line, in :mod:`eofnn.studies`; the modules of the
same names here are deprecated aliases, for one release.
"""
