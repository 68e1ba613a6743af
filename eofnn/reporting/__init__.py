"""Reports and figures: the only part of eofnn that imports matplotlib.

It draws what the floors below computed (experiment results, robustness maps, Pareto fronts, stability analyses,
replays, sweeps) and never chooses a backend: the command line does that once, at its entry
(:func:`eofnn.cli.main.main`); a library user's own backend is left alone.
"""
