"""eofnn's controllers inside other simulators' closed loops (``docs/interop.md``).

- :mod:`eofnn.interop.loop`: the shared part: a simulator adapter protocol, the closed loop with its delay line,
  controllers (integrator with dither, the exported runtime filter, a torch controller), telemetry out;
- :mod:`eofnn.interop.study`: record -> identify -> fit closed-loop EOF -> replay -> run in the simulator's loop
  against its best-gain integrator;
- :mod:`eofnn.interop.oopao` (needs ``pip install 'eofnn[interop]'``) and :mod:`eofnn.interop.hcipy`: the
  adapters. Neither simulator is imported before an adapter is made: ``import eofnn`` needs neither.
"""
