"""Loading-event rules and the plate speed: does breakage depend on how fast the plate moves?

The Tavares model damages a particle at the end of each loading event and restarts its
stressing energy from zero (spec 5.4-5.5). When an event ends is an [A] choice,
``breakage.event_end_rule``:

- ``quiet`` (the spec's): after ``breakage.event_end_steps`` (10) steps in a row without a
  loading contact. In a bed the contacts jostle at their own frequency, so events end at a
  rate per unit of time; a slower plate (more steps per unit of strain) ends more of them
  per unit of strain, throws away more stressing energy and breaks fewer particles.
- ``release``: once no contact presses on the particle. No time scale.

``run`` calenders the sweep preset's electrode (one cell size, ``--cell``) at each plate
speed of ``--inertial`` under each rule of ``--rules`` for ``--seeds`` seeds, one CPU
thread a run, ``--jobs`` runs side by side. Each finished run appends one JSON line to
``<out>/runs.jsonl`` (rule, inertial number, seed, breakage events, event ends per active
particle, calendering steps, wall seconds, top pressure at 5 / 10 / 15 / 19.5 um); a rerun
skips what is there, so a killed study resumes. ``report`` writes the means and standard
deviations per rule and speed, and for each rule the change from the fastest to the
slowest plate with its standard error (JSON and a Markdown table).

    python benchmarks/event_rules.py run --out studies/event_rules --cell 30 --seeds 3
    python benchmarks/event_rules.py report --out studies/event_rules \
        --json benchmarks/results/event_rules_30um.json
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
DEPTHS_UM = (5.0, 10.0, 15.0, 19.5)


def _key(rule: str, inertial: float, seed: int) -> str:
    return f"{rule}-I{inertial:g}-s{seed}"


def _done(out: Path) -> dict[str, dict]:
    path = out / "runs.jsonl"
    if not path.exists():
        return {}
    rows = [json.loads(line) for line in path.read_text().splitlines() if line.strip()]
    return {_key(r["rule"], r["inertial"], r["seed"]): r for r in rows}


def pressure_at(depth: np.ndarray, value: np.ndarray, um: float, half_width: float = 0.25e-6
                ) -> float:
    """Mean top pressure [Pa] of the samples within ``half_width`` of ``um`` micrometres."""
    m = np.abs(depth - um * 1e-6) < half_width
    return float(value[m].mean()) if m.any() else float("nan")


def cmd_one(args) -> int:
    """One run (a subprocess of ``run``): prints its JSON line."""
    from calendaring import CalenderRun, load_preset, read_run, with_overrides

    cfg = with_overrides(load_preset(args.preset), {
        "domain.cell_x": args.cell * 1e-6, "domain.cell_y": args.cell * 1e-6,
        "protocol.inertial_number": args.inertial, "numerics.seed": args.seed,
        "numerics.threads": 1, "breakage.event_end_rule": args.rule})
    ends = {}

    class Counted(CalenderRun):
        def _finish_calender(self) -> None:  # the pool before the run file is written
            p = self.sim.pool
            n = p.n_slots[None]
            active = (p.alive.to_numpy()[:n] == 1) & (p.material.to_numpy()[:n] == 0)
            ends["n"] = int(active.sum())
            ends["ended"] = int(p.event_id.to_numpy()[:n][active].sum())
            ends["damaged"] = int(p.damage_events.to_numpy()[:n][active].sum())
            super()._finish_calender()

    path = Path(args.file)
    t0 = time.perf_counter()
    Counted(cfg, path, progress=False, preset=args.preset).execute()
    wall = time.perf_counter() - t0
    rec = read_run(path)
    depth, value = np.asarray(rec.pressure["depth"]), np.asarray(rec.pressure["value"])
    row = {"rule": args.rule, "inertial": args.inertial, "seed": args.seed,
           "cell_um": args.cell, "events": len(rec.breakage["parent_id"]),
           "active_particles_end": ends["n"],
           "event_ends_per_particle": ends["ended"] / max(ends["n"], 1),
           "damaging_ends_per_particle": ends["damaged"] / max(ends["n"], 1),
           "steps": int(rec.info["calender_steps"]), "wall_s": wall,
           "software_version": rec.software_version,
           "pressure_mpa": {f"{um:g}": pressure_at(depth, value, um) / 1e6
                            for um in DEPTHS_UM}}
    path.unlink()
    print(json.dumps(row), flush=True)
    return 0


def cmd_run(args) -> int:
    from bench_dem import _software  # this folder is on sys.path when run as a script

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "provenance.jsonl").open("a").write(json.dumps(
        {"date": time.strftime("%Y-%m-%d %H:%M:%S"), "argv": sys.argv, **_software()}) + "\n")
    done = _done(out)
    todo = [(r, i, s) for s in range(args.seeds) for i in args.inertial for r in args.rules
            if _key(r, i, s) not in done]
    print(f"[rules] {len(done)} runs done, {len(todo)} to run, {args.jobs} at a time",
          flush=True)
    t0 = time.perf_counter()

    def one(job):
        rule, inertial, seed = job
        cmd = [sys.executable, __file__, "one", "--rule", rule, "--inertial", str(inertial),
               "--seed", str(seed), "--cell", str(args.cell), "--preset", args.preset,
               "--file", str(out / f"{_key(rule, inertial, seed)}.h5")]
        res = subprocess.run(cmd, capture_output=True, text=True)
        if res.returncode != 0:
            print(f"[rules] {_key(*job)} failed:\n{res.stderr[-2000:]}", flush=True)
            return None
        row = json.loads(res.stdout.strip().splitlines()[-1])
        with (out / "runs.jsonl").open("a") as f:  # one short line: an atomic append
            f.write(json.dumps(row) + "\n")
        print(f"[rules] {_key(*job)}: {row['events']} events, "
              f"{row['wall_s']:.0f} s (study {time.perf_counter() - t0:.0f} s)", flush=True)
        return row

    with ThreadPoolExecutor(args.jobs) as pool:
        rows = list(pool.map(one, todo))
    return 0 if all(r is not None for r in rows) else 3


def summarise(rows: list[dict]) -> dict:
    """Mean, sd and count per (rule, inertial) of the scalar columns and the pressures; per
    rule the change from the fastest to the slowest plate with its standard error."""
    groups: dict[tuple, list[dict]] = {}
    for r in rows:
        groups.setdefault((r["rule"], float(r["inertial"])), []).append(r)

    def stats(vals):
        v = np.asarray(vals, float)
        return {"mean": float(v.mean()), "sd": float(v.std(ddof=1)) if len(v) > 1 else None,
                "n": len(v)}

    cases = []
    for (rule, inertial), g in sorted(groups.items(), key=lambda kv: (kv[0][0], -kv[0][1])):
        case = {"rule": rule, "inertial": inertial, "seeds": sorted(r["seed"] for r in g)}
        for col in ("events", "event_ends_per_particle", "damaging_ends_per_particle",
                    "steps", "wall_s"):
            case[col] = stats([r[col] for r in g])
        case["pressure_mpa"] = {um: stats([r["pressure_mpa"][um] for r in g])
                                for um in g[0]["pressure_mpa"]}
        cases.append(case)
    effects = []
    for rule in sorted({c["rule"] for c in cases}):
        mine = [c for c in cases if c["rule"] == rule]
        if len(mine) < 2:
            continue
        fast, slow = mine[0], mine[-1]

        def change(a, b):
            se = None
            if a["sd"] is not None and b["sd"] is not None:
                se = float(np.sqrt(a["sd"] ** 2 / a["n"] + b["sd"] ** 2 / b["n"]))
            d = b["mean"] - a["mean"]
            return {"slow_minus_fast": d, "se": se,
                    "relative": d / a["mean"] if a["mean"] else None,
                    "z": d / se if se else None}

        effects.append({"rule": rule, "fast": fast["inertial"], "slow": slow["inertial"],
                        "events": change(fast["events"], slow["events"]),
                        "pressure_mpa": {um: change(fast["pressure_mpa"][um],
                                                    slow["pressure_mpa"][um])
                                         for um in fast["pressure_mpa"]}})
    return {"cases": cases, "speed_effect": effects}


def _pm(s, fmt="{:.1f}"):
    return fmt.format(s["mean"]) + ("" if s["sd"] is None else " +- " + fmt.format(s["sd"]))


def markdown(summary: dict) -> str:
    lines = ["| rule | I | seeds | events | event ends / particle | P 5 / 10 / 15 / 19.5 um "
             "[MPa] | wall s |", "|---|---|---|---|---|---|---|"]
    for c in summary["cases"]:
        p = " / ".join(_pm(c["pressure_mpa"][k]) for k in c["pressure_mpa"])
        lines.append(f"| {c['rule']} | {c['inertial']:g} | {len(c['seeds'])} | "
                     f"{_pm(c['events'])} | {_pm(c['event_ends_per_particle'])} | {p} | "
                     f"{c['wall_s']['mean']:.0f} |")
    lines += ["", "| rule | fast -> slow | events | z | P 15 um [MPa] | z | P 19.5 um [MPa] | z |",
              "|---|---|---|---|---|---|---|---|"]
    for e in summary["speed_effect"]:
        cells = []
        for ch in (e["events"], e["pressure_mpa"]["15"], e["pressure_mpa"]["19.5"]):
            rel = "" if ch["relative"] is None else f" ({100 * ch['relative']:+.0f} %)"
            z = "-" if ch["z"] is None else f"{ch['z']:+.1f}"
            cells += [f"{ch['slow_minus_fast']:+.1f}{rel}", z]
        lines.append(f"| {e['rule']} | {e['fast']:g} -> {e['slow']:g} | " + " | ".join(cells)
                     + " |")
    return "\n".join(lines) + "\n"


def cmd_report(args) -> int:
    from calendaring import write_json

    out = Path(args.out)
    rows = list(_done(out).values())
    if not rows:
        print(f"[rules] no finished runs in {out}", file=sys.stderr)
        return 2
    summary = summarise(rows)
    prov = out / "provenance.jsonl"
    summary["provenance"] = ([json.loads(x) for x in prov.read_text().splitlines() if x]
                             if prov.exists() else [])
    summary["runs"] = sorted(rows, key=lambda r: (r["rule"], -r["inertial"], r["seed"]))
    path = Path(args.json)
    write_json(path, summary)
    md = markdown(summary)
    path.with_suffix(".md").write_text(md)
    print(md)
    return 0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    run = sub.add_parser("run")
    run.add_argument("--out", required=True, help="study folder (runs.jsonl; resumable)")
    run.add_argument("--cell", type=float, default=30.0, help="cell side [um]")
    run.add_argument("--inertial", type=float, nargs="+", default=[1.5e-2, 1.5e-3])
    run.add_argument("--rules", nargs="+", default=["quiet", "release"])
    run.add_argument("--seeds", type=int, default=3)
    run.add_argument("--jobs", type=int, default=2, help="runs side by side")
    run.add_argument("--preset", default="sweep")
    one = sub.add_parser("one")
    for name, kind in (("--rule", str), ("--inertial", float), ("--seed", int),
                       ("--cell", float), ("--preset", str), ("--file", str)):
        one.add_argument(name, type=kind, required=True)
    rep = sub.add_parser("report")
    rep.add_argument("--out", required=True)
    rep.add_argument("--json", default=str(HERE / "results" / "event_rules.json"))
    args = ap.parse_args(argv)
    return {"run": cmd_run, "one": cmd_one, "report": cmd_report}[args.cmd](args)


if __name__ == "__main__":
    raise SystemExit(main())
