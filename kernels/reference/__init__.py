"""Pure torch/NumPy versions of every kernel: the oracles of tests and the baselines of benchmarks."""
