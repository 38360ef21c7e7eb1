"""Scenario studies (rockwave/app/sweep.py): a 2x2 sweep of the tiny 2D slide through the local process pool and
through a local Ray instance gives identical tables; a study killed mid-way finishes only what was missing; bad
values are all reported before anything runs; a failing scenario and a dying worker are recorded while the
others finish."""

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from rockwave.app import sweep

ROOT = Path(__file__).resolve().parent.parent
TINY = ROOT / "scenes" / "slide_2d_tiny.toml"


def _study(tmp_path: Path, name="study.toml", duration=0.02, values=(2000.0, 2600.0), extra="") -> Path:
    p = tmp_path / name
    p.write_text(f"""
[study]
scene = "{TINY}"
results = "results"
duration_s = {duration}
{extra}
[[vary]]
key = "blocks[slide].density_kg_m3"
values = [{", ".join(repr(v) for v in values)}]
[[vary]]
key = "blocks[slide].material.friction_angle_deg"
range = [10.0, 20.0]
steps = 2
""")
    return p


def test_scenarios_and_keys(tmp_path):
    st = sweep.load_study(_study(tmp_path))
    assert [sc.params for sc in st.scenarios] == [
        {"blocks[slide].density_kg_m3": a, "blocks[slide].material.friction_angle_deg": b}
        for a in (2000.0, 2600.0) for b in (10.0, 20.0)]
    blk = [b for b in st.scenarios[3].data["blocks"] if b["name"] == "slide"][0]
    assert blk["density_kg_m3"] == 2600.0 and blk["material"]["friction_angle_deg"] == 20.0
    assert st.scenarios[0].data["simulation"]["duration_s"] == 0.02
    assert st.scenarios[0].data["output"]["usd"] == ""  # not kept
    assert len({sc.id for sc in st.scenarios}) == 4
    script = sweep.slurm_script(st).read_text()  # a job array for sites without Ray: one task per scenario
    assert "#SBATCH --array=0-3" in script and '--only "$SLURM_ARRAY_TASK_ID"' in script
    # Latin hypercube: each key's n strata hit once
    lhs = _study(tmp_path, "lhs.toml").read_text().replace('results = "results"', 'results = "r2"\nsample = "lhs"\nn = 5')
    lhs = lhs.replace("steps = 2\n", "").replace("values = [2000.0, 2600.0]", "range = [2000.0, 3000.0]")
    (tmp_path / "lhs.toml").write_text(lhs)
    st = sweep.load_study(tmp_path / "lhs.toml")
    dens = sorted(sc.params["blocks[slide].density_kg_m3"] for sc in st.scenarios)
    assert [int((d - 2000.0) / 200.0) for d in dens] == [0, 1, 2, 3, 4]
    assert sweep.load_study(tmp_path / "lhs.toml").scenarios[2].params == st.scenarios[2].params  # seeded


def test_bad_values_reported_before_anything_runs(tmp_path):
    p = _study(tmp_path, values=(2000.0, -5.0, "heavy"))
    with pytest.raises(sweep.StudyError) as e:
        sweep.load_study(p)
    text = str(e.value)
    assert text.startswith(str(p))
    assert "scenario 2 (blocks[slide].density_kg_m3 = -5" in text and "scenario 3 (" in text  # both friction values
    assert "scenario 4 (blocks[slide].density_kg_m3 = heavy" in text and "expected a number" in text
    assert "scenario 0" not in text and "scenario 1 " not in text
    assert not (tmp_path / "results").exists()  # nothing ran
    # a key that names nothing, and the CLI's exit code
    bad = _study(tmp_path, "bad.toml").read_text().replace("blocks[slide].material", "blocks[rockslide].material")
    (tmp_path / "bad.toml").write_text(bad)
    r = subprocess.run([sys.executable, "-m", "rockwave", "sweep", str(tmp_path / "bad.toml")], capture_output=True, text=True)
    assert r.returncode == 2 and "no entry of blocks is named 'rockslide'" in r.stderr


def _table(res_dir: Path):
    import pyarrow.parquet as pq

    return (res_dir / "study.csv").read_text(), pq.read_table(res_dir / "study.parquet")


def test_local_and_ray_give_identical_tables(tmp_path):
    p = _study(tmp_path)
    a = sweep.run_study(p, out=tmp_path / "local", workers=2, progress=False)
    assert a.ran == 4 and a.failed == 0 and [r["status"] for r in a.rows] == ["ok"] * 4
    csv_a, pq_a = _table(tmp_path / "local")
    rows = {r["index"]: r for r in a.rows}
    assert rows[0]["slide.peak_speed_m_s"] > 0 and "g0.2.max_crest_m" in rows[0]
    assert rows[0]["slide.runout_m"] > rows[1]["slide.runout_m"]  # friction 10 degrees slides further than 20
    assert (tmp_path / "local" / "max_wave_height.png").is_file() and (tmp_path / "local" / "runup.png").is_file()
    ray = pytest.importorskip("ray", reason="ray is not installed (pip install 'rockwave[sweep]')")
    try:
        b = sweep.run_study(p, out=tmp_path / "ray", executor="ray", ray_init={"num_cpus": 2, "include_dashboard": False},
                            progress=False)
    finally:
        ray.shutdown()
    assert b.ran == 4 and b.failed == 0
    csv_b, pq_b = _table(tmp_path / "ray")
    assert csv_a == csv_b
    assert pq_a.equals(pq_b)


def test_killed_study_resumes_only_what_was_missing(tmp_path):
    p = _study(tmp_path, duration=0.05)
    res = tmp_path / "results" / "scenarios"
    proc = subprocess.Popen([sys.executable, "-m", "rockwave", "sweep", str(p), "--workers", "1", "--quiet"],
                            start_new_session=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.time() + 120
        while time.time() < deadline and len(list(res.glob("*/result.json"))) < 1:
            time.sleep(0.05)
    finally:
        os.killpg(proc.pid, signal.SIGKILL)  # the study and its worker
        proc.wait()
    done = {f.parent.name: f.stat().st_mtime_ns for f in res.glob("*/result.json")}
    assert 1 <= len(done) < 4
    r = sweep.run_study(p, executor="inline", progress=False, plots=False)
    assert r.skipped == len(done) and r.ran == 4 - len(done)
    assert all((res / k / "result.json").stat().st_mtime_ns == t for k, t in done.items())  # not run again
    assert [row["status"] for row in r.rows] == ["ok"] * 4
    again = sweep.run_study(p, executor="inline", progress=False, plots=False)
    assert again.ran == 0 and again.skipped == 4


def flaky(config):
    """A stand-in for run_scenario: scenario 1 raises, scenario 2 kills its worker process."""
    if config["index"] == 1:
        raise RuntimeError("boom")
    if config["index"] == 2:
        os._exit(3)
    return {"id": config["id"], "index": config["index"], "params": config["params"], "status": "ok", "error": "",
            "metrics": {"x": float(config["index"])}, "wall_s": 0.0}


def test_failures_and_dead_workers_are_recorded(tmp_path):
    st = sweep.load_study(_study(tmp_path))
    configs = [sweep.scenario_config(st, sc) for sc in st.scenarios]
    got = {}
    sweep.run_local(configs, ["cpu", "cpu"], lambda res, running: got.__setitem__(res["index"], res), fn=flaky)
    assert sorted(got) == [0, 1, 2, 3]
    assert got[0]["status"] == got[3]["status"] == "ok"
    assert got[1]["status"] == "failed" and "boom" in got[1]["error"]
    assert got[2]["status"] == "failed" and "worker process died" in got[2]["error"]
    # a scenario that fails inside run_scenario is a result too, written atomically
    cfg = dict(configs[0], scene=dict(configs[0]["scene"], simulation={"dimension": 2, "duration_s": -1.0}))
    res = sweep.run_scenario(cfg)
    assert res["status"] == "failed" and "duration_s" in res["error"]
    assert json.loads((Path(cfg["out_dir"]) / "result.json").read_text())["status"] == "failed"
