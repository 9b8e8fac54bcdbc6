"""Moved to gsa.bench.lift (a benchmark that runs the aligner belongs above gsa.align, not
inside gsa.features, which gsa.align uses). `python -m gsa.features.bench_lift` still runs it.
run_module rather than an import keeps gsa.features free of any dependency on gsa.bench."""

import runpy

if __name__ == "__main__":
    runpy.run_module("gsa.bench.lift", run_name="__main__", alter_sys=True)
