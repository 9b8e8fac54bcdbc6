"""Service benchmarks: each starts a deployment of its own (redis-server, `gsa serve`, `gsa worker`,
Chromium) in a temp folder and prints its numbers. Run from the repository root:
`python -m benchmarks.service.NAME` (docs/benchmarks.md, "Service benchmarks")."""
