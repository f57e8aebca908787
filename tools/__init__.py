"""Developer tools: renders, diagnostics, ablations, benchmarks and snapshot selection, run as
`python -m tools.<name>` from the repository root. Nothing in `models/` or `service/` imports them
at run time (LPN training renders its progress with `tools.lpn_demo`, where it can)."""
