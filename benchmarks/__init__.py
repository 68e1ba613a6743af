"""Benchmarks of eofnn against baselines timed in the same run.

Run everything with ``python -m benchmarks.run [--quick] [--out benchmarks/results.json]``; see
``benchmarks/README.md`` for what each row means. Every figure is a *ratio* against a baseline measured in the
same process, minutes apart at most, because absolute times on a shared machine are mostly noise.
"""
