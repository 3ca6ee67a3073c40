"""Tools that measure speed: the benchmarks behind BENCHMARKS.md."""
