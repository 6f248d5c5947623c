"""`twin bench`: benchmarks that print figures (throughput, fidelity, footprint). See docs/performance.md."""
