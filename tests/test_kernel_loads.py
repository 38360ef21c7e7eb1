"""Each Warp module of rockwave.kernels is built once per device in a run that uses every feature:
a basic scene (gauges, particle reorder and unsort, density diffusion), a Ghost SPH scene, a coupled
fluid-block scene and the fluid surface. A module that gains a kernel or an overload after its first
load (a generic kernel specialised at launch, a kernel defined lazily) or that is launched at two block
sizes is built again under a new hash: one full build each time, on every device.

The run goes in a subprocess with a fresh kernel cache and Warp's load messages on; each message
"Module <name> <hash> load on device '<device>' took ..." names the module's hash, and every
rockwave.kernels module must show a single hash per device. On a CUDA test device
(ROCKWAVE_TEST_DEVICE) this also covers the launches whose block size differs on CUDA."""

from __future__ import annotations

import os
import re
import subprocess
import sys
import textwrap
from collections import defaultdict

from conftest import DEVICE
from helpers import ROOT

PROBE = textwrap.dedent(
    """
    import sys, tomllib
    import numpy as np
    import warp as wp

    wp.config.quiet = False
    wp.config.kernel_cache_dir = sys.argv[2]
    import rockwave
    from rockwave.output.surface import SurfaceExtractor
    from tests.helpers import ROOT, tank_2d

    device = sys.argv[1]
    basic = tank_2d(width=0.3, depth=0.1, height=0.2, spacing=0.01, density_diffusion=0.1)
    basic["output"] = {"gauges": [{"name": "h", "kind": "height", "position_m": [0.1, 0.0]},
                                  {"name": "p", "kind": "pressure", "position_m": [0.1, 0.02]}]}
    ghost = tomllib.loads((ROOT / "scenes" / "ghost_dam_break_case1.toml").read_text())
    coupled = tomllib.loads((ROOT / "scenes" / "floating_box_2d.toml").read_text())
    for name, d, steps in (("basic", basic, 12), ("ghost", ghost, 3), ("coupled", coupled, 3)):
        print("probe scene", name, flush=True)
        sim = rockwave.Simulation(rockwave.parse_scene(d), device=device)
        sim.step_many(steps)  # a reorder chunk (reorder_interval steps) where the solver has one
        sim.advance(2 * sim.dt)
        sim.gauges(), sim.positions(), sim.densities()  # the readers scatter into the seeded order
        sim.fluid_solver.unsort(sim.state)
        m, nf = sim.fluid, sim.n_fluid
        for field in ("colour", "metaball"):
            ex = SurfaceExtractor(sim.scene.dim, m.spacing, m.fluid_mass, device, field=field)
            ex.extract(sim.state.x[:nf], sim.state.rho)
    print("probe done", flush=True)
    """
)

LOAD = re.compile(r"Module (\S+) ([0-9a-f]+) load on device '([^']+)'")


def test_each_kernel_module_is_built_once_per_device(tmp_path):
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    r = subprocess.run([sys.executable, "-c", PROBE, DEVICE, str(tmp_path / "kernels")], cwd=ROOT, env=env,
                       capture_output=True, text=True, timeout=600)
    out = r.stdout + r.stderr
    assert r.returncode == 0, out[-4000:]
    assert "probe done" in out
    hashes = defaultdict(set)
    for name, h, device in LOAD.findall(out):
        hashes[(name, device)].add(h)
    ours = {k: v for k, v in hashes.items() if k[0].startswith("rockwave.kernels")}
    # the run reached every kernel module of the features above
    names = {k[0] for k in ours}
    for module in ("sph.fluid", "sph.fluid_force_pass", "sph.diffusion", "sph.ghost", "coupling.penalty", "dda.blocks",
                   "output.surface", "sim.readers"):  # (kernels/ mirrors the packages since 0995fe4)
        assert f"rockwave.kernels.{module}" in names, (module, sorted(names))
    rebuilt = {f"{n} on {d}": sorted(v) for (n, d), v in ours.items() if len(v) > 1}
    assert not rebuilt, rebuilt
