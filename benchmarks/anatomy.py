"""Where the time of one EABC training step goes: XLA's own per-operation timings.

    python benchmarks/anatomy.py                 # K = 10, hopper shapes, both cores
    python benchmarks/anatomy.py --k 2 --top 20
    python benchmarks/anatomy.py --single-thread # one core, as one process per core runs

Runs the real compiled training chunk (the one ``speed.py`` times) under the JAX profiler, reads
every XLA operation's run time from the trace and its FLOPs from the compiled program's HLO, and
prints the step's time split into matrix products (with the GFLOP/s each reaches), layout copies
(transposes) and elementwise work (bias, ReLU, their gradients, Adam, Polyak averaging, sampling),
beside the machine's XLA large-product peak (machine.py) measured in the same run. An operation's GFLOP/s is its FLOPs over
its own duration: XLA runs independent operations (a layer's input and weight gradients) side by
side, each on part of the cores, and those read lower than they would alone. Profiling slows the
step a little; the split is what matters. The machine is noisy: compare splits across runs.
"""

from __future__ import annotations

import argparse
import collections
import dataclasses
import functools
import glob
import gzip
import json
import math
import os
import re
import sys
import tempfile
import time

INSTRUCTION = re.compile(r"^\s*(?:ROOT )?%(\S+) = (\w+)\[([\d,]*)\]\S* (\w[\w-]*)\(([^)]*)\)(.*)$")
COMPUTATION = re.compile(r"^(?:ENTRY )?%(\S+) ")


def parse_hlo(text: str) -> tuple[dict, dict]:
    """Instructions per computation: ``{computation: {name: (shape, opcode, operands, attrs)}}``,
    and which computation each instruction lives in."""
    computations: dict[str, dict] = {}
    current = None
    for line in text.splitlines():
        if not line.startswith(" ") and "{" in line:
            match = COMPUTATION.match(line)
            current = computations.setdefault(match.group(1), {}) if match else None
            continue
        match = INSTRUCTION.match(line)
        if match and current is not None:
            name, _, dims, opcode, operands, attrs = match.groups()
            shape = tuple(int(d) for d in dims.split(",") if d)
            names = re.findall(r"%([\w.\-]+)", operands)
            current[name] = (shape, opcode, names, attrs)
    return computations, {n: c for c, insts in computations.items() for n in insts}


def dot_flops(instructions: dict, name: str) -> float:
    """2 x output size x contracted size of a ``dot`` instruction."""
    shape, _, operands, attrs = instructions[name]
    lhs = instructions[operands[0]][0]
    contracting = re.search(r"lhs_contracting_dims=\{([\d,]*)\}", attrs).group(1)
    contracted = math.prod(lhs[int(d)] for d in contracting.split(",") if d)
    return 2.0 * math.prod(shape) * contracted


def dot_form(instructions: dict, name: str) -> str:
    """``NN`` for ``x @ w``, ``NT`` for ``x @ w.T``, ``TN`` for ``x.T @ y`` (contracted axes)."""
    _, _, operands, attrs = instructions[name]
    lhs_rank = len(instructions[operands[0]][0])
    lhs = re.search(r"lhs_contracting_dims=\{(\d+)", attrs)
    rhs = re.search(r"rhs_contracting_dims=\{(\d+)", attrs)
    batch = (
        len(re.search(r"lhs_batch_dims=\{([\d,]*)", attrs).group(1).split(","))
        if ("lhs_batch_dims" in attrs)
        else 0
    )
    left = "N" if int(lhs.group(1)) == lhs_rank - 1 else "T"
    right = "N" if int(rhs.group(1)) == batch else "T"
    return left + right


def op_dots(computations: dict, owner: dict, name: str) -> list[tuple[dict, str]]:
    """The ``dot`` instructions a top-level operation runs (itself, or inside its fusion)."""
    _, opcode, _, attrs = computations[owner[name]][name]
    if opcode == "dot":
        return [(computations[owner[name]], name)]
    if opcode == "fusion":
        body = computations.get(re.search(r"calls=%([\w.\-]+)", attrs).group(1), {})
        return [(body, n) for n, inst in body.items() if inst[1] == "dot"]
    return []


def category(name: str, flops: float, opcode: str) -> str:
    if flops:
        return "matrix products"
    if "transpose" in name or opcode in ("copy", "transpose") or name.startswith("copy"):
        return "layout copies (transposes)"
    return "elementwise and other"


def profile(compiled, args) -> tuple[dict[str, float], dict[str, int], float]:
    """Total microseconds and executions per XLA operation over one run of ``compiled``, and the
    run's wall-clock seconds."""
    import jax

    with tempfile.TemporaryDirectory() as tmp:
        jax.profiler.start_trace(tmp, create_perfetto_trace=True)
        start = time.perf_counter()
        jax.block_until_ready(compiled(*args))
        wall = time.perf_counter() - start
        jax.profiler.stop_trace()
        (path,) = glob.glob(f"{tmp}/**/perfetto_trace.json.gz", recursive=True)
        with gzip.open(path) as f:
            trace = json.load(f)
    events = trace["traceEvents"] if isinstance(trace, dict) else trace
    totals: dict[str, float] = collections.Counter()
    counts: dict[str, int] = collections.Counter()
    for event in events:
        if event.get("ph") == "X":
            totals[event["name"]] += event.get("dur", 0.0)
            counts[event["name"]] += 1
    return totals, counts, wall


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--k", type=int, default=10, help="ensemble size")
    parser.add_argument("--env", default="hopper", choices=("hopper", "halfcheetah"))
    parser.add_argument("--steps", type=int, default=500, help="steps in the profiled chunk")
    parser.add_argument("--top", type=int, default=12, help="operations listed one by one")
    parser.add_argument(
        "--single-thread", action="store_true", help="one thread (set before JAX starts)"
    )
    parser.add_argument("--dump-hlo", metavar="FILE", help="write the compiled program's HLO text")
    args = parser.parse_args()
    sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
    import machine
    from speed import SHAPES, fake_data, single_thread_env, step_flops

    if args.single_thread:  # before JAX starts
        os.environ.update(single_thread_env(0))

    import jax

    from eabc.agents import eabc
    from eabc.training.chunks import train_chunk

    obs_dim, act_dim = SHAPES[args.env]
    data = fake_data(obs_dim, act_dim)
    config = dataclasses.replace(eabc.PRESETS["eabc"], num_critics=args.k, confidence_level=0.5)
    state = eabc.init(jax.random.PRNGKey(0), obs_dim, act_dim, config)
    update = functools.partial(eabc.update, config=config, max_action=1.0)
    key = jax.random.PRNGKey(1)
    chunk = functools.partial(
        train_chunk,
        data=data,
        update=update,
        batch_size=256,
        length=args.steps,
        period=config.policy_freq,
    )
    compiled = jax.jit(chunk).lower(state, key).compile()
    computations, owner = parse_hlo(compiled.as_text())
    if args.dump_hlo:
        with open(args.dump_hlo, "w") as f:
            f.write(compiled.as_text())
    jax.block_until_ready(compiled(state, key))  # warm up
    start = time.perf_counter()
    jax.block_until_ready(compiled(state, key))
    rate = args.steps / (time.perf_counter() - start)
    totals, counts, wall = profile(compiled, (state, key))
    peak, _ = machine.xla_peak()  # the ceiling: XLA's own large products

    rows = []
    for name, micros in totals.items():
        if name not in owner:
            continue  # runtime events (executor, waits), not operations of the program
        shape, opcode, _, _ = computations[owner[name]][name]
        dots = op_dots(computations, owner, name)
        flops = sum(dot_flops(*d) for d in dots) * counts[name]  # over the whole chunk
        form = "/".join(dot_form(*d) for d in dots)
        rows.append((name, form or opcode, shape, micros, flops, category(name, flops, opcode)))
    total = sum(r[3] for r in rows)
    per_step = lambda micros: micros / args.steps / 1e3  # noqa: E731  ms per step

    threads = "1 thread" if args.single_thread else f"{os.cpu_count()} cores"
    print(f"EABC K = {args.k}, {args.env} shapes, batch 256, {threads}: {rate:.1f} steps/s "
          f"unprofiled; XLA large-product peak {peak:.0f} GFLOP/s; step_flops {step_flops(obs_dim, act_dim, args.k) / 1e9:.2f} GFLOP")  # fmt: skip
    matmul_flops = sum(r[4] for r in rows) / args.steps
    print(
        f"matmul FLOPs counted from the compiled program: {matmul_flops / 1e9:.2f} GFLOP per step"
    )
    print(f"profiled run: {1e3 * wall / args.steps:.2f} ms per step wall-clock, operations busy "
          f"{per_step(total):.2f} ms per step (more than the wall clock where XLA runs independent "
          f"operations side by side, each on part of the cores)\n")  # fmt: skip
    print(f"{'part':30s} {'ms/step':>8s} {'share':>6s} {'GFLOP/s':>8s}")
    by_category: dict[str, list[float]] = collections.defaultdict(lambda: [0.0, 0.0])
    for *_, micros, flops, cat in rows:
        by_category[cat][0] += micros
        by_category[cat][1] += flops
    for cat, (micros, flops) in sorted(by_category.items(), key=lambda kv: -kv[1][0]):
        speed = f"{flops / micros / 1e3:8.0f}" if flops else f"{'':8s}"
        print(f"{cat:30s} {per_step(micros):8.2f} {100 * micros / total:5.0f}% {speed}")
    print(
        f"\n{'operation':28s} {'kind':24s} {'form':5s} {'shape':18s} {'ms/step':>8s} {'GFLOP/s':>8s}"
    )
    for name, form, shape, micros, flops, cat in sorted(rows, key=lambda r: -r[3])[: args.top]:
        speed = f"{flops / micros / 1e3:8.0f}" if flops else ""
        form = form if flops else ""
        print(
            f"{name:28s} {cat[:24]:24s} {form:5s} {str(list(shape)):18s} {per_step(micros):8.2f} {speed}"
        )


if __name__ == "__main__":
    main()
