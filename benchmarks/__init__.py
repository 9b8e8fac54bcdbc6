"""GSA's benchmarks: run from a checkout of the repository, never part of the installed package.

benchmarks/              `gsa bench`'s protocols (protocols.run_protocols, the verb's entry point)
                         with their pair generators, judges and tables (pairs, peers, records,
                         tables, scene, site, category_real, real_captures, guided, nway,
                         ablation, speed, formats_io), and the measurement modules run as
                         `python -m benchmarks.NAME` (coarse_speed, cli_speed, render_speed,
                         fine_speed, fine_loss_floor, cuda_speed, lift, ply_memory, scene_sizes,
                         frames, recon, photo_halves)
benchmarks/service/      scripts that start a deployment and measure the service
                         (`python -m benchmarks.service.NAME`)

Every one is listed, with its command and current numbers, in docs/benchmarks.md. The library
(gsa/) and the service (service/) never import this package (tests/test_import_graph.py); the
`gsa bench` verb looks it up by name beside the gsa/ it was imported from.
"""
