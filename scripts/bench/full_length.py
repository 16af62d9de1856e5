#!/usr/bin/python3
"""The whole male at full length (docs/BENCHMARKS.md 'The whole male at full length'): male-shaped
stacks of N distinct 2048x1216 slices as NLM ships them (planar .raw colour, 512x512 CT at 1 mm,
colour-coded segmentation; four blocks with a jump at each boundary and a brightness step per
block, twelve black slices), streamed by `vispack-phantom --truth-every K` (no truth volume in
memory), and a Visible-Korean-sized stack (4368x2912); each run through
`vispack-run CONFIG --threads 2` from the raw files to .vpk and .vdb once with a cold page cache
(sync; echo 3 > /proc/sys/vm/drop_caches, as root) and once warm, then scored against the truth
sample (vispack-score).

Per run: wall, CPU (user + system) and peak resident memory of the process (/usr/bin/time -v), and
per stage (the stage whose progress lines the run prints last: register, then the one pass that
computes mask, labels and appends to the pack, the pack's end, vdb) its wall, CPU and largest
resident memory sampled from /proc/PID every 0.2 s; bytes read from and written to storage and
through read()/write() (/proc/PID/io), file sizes, the load average. Stops with a clear message
when the free space of the work folder would fall under --keep-free-gb (checked before each
generation and run, and every 0.2 s during a run: the run is killed).

Usage: full_length.py --bin DIR --work DIR --results DIR [--slices "128 512 1871"] [--korean N]
                      [--female N] [--truth-every K] [--keep-free-gb GB] [--keep-stacks] [--no-cold]
                      [--generator BIN] [--generate-only]
The female's shape (--female N): the male phantom's body over N colour slices with a CT slice at
every third (`--ct-every 3`, as the VH female's 0.33 mm colour over its 1 mm CT).
Writes RESULTS/full_length.json (and the logs beside it); report: full_length_report.py."""
import argparse
import hashlib
import json
import os
import shutil
import signal
import subprocess
import sys
import threading
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import machine  # noqa: E402
from time_v import read_time_v  # noqa: E402

SAMPLE_S = 0.2
# Output bytes per slice of a run (work folder + .vpk + .vdb), a generous bound from the 16-slice
# male (about 5 MB per 2048x1216 slice): checked against the free space before a run.
RUN_BYTES_PER_PIXEL = 3.0


class DiskFull(Exception):
    pass


def log(msg):
    print(f"full_length [{time.strftime('%H:%M:%S')}] {msg}", file=sys.stderr, flush=True)


def free_bytes(path):
    st = os.statvfs(path)
    return st.f_bavail * st.f_frsize


def need_space(path, needed, keep_free, what):
    free = free_bytes(path)
    if free - needed < keep_free:
        raise DiskFull(f"{what}: needs about {needed / 1e9:.1f} GB in {path}, which has "
                       f"{free / 1e9:.1f} GB free; at least {keep_free / 1e9:.0f} GB must stay free "
                       "(--keep-free-gb): stopped before it")


def du(path):
    total = 0
    for root, _, files in os.walk(path):
        for f in files:
            try:
                total += os.lstat(os.path.join(root, f)).st_size
            except OSError:
                pass
    return total


def sha256(path):
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def drop_caches():
    """Cold page cache: write back, then drop the clean pages (root only). Returns whether it ran."""
    subprocess.run(["sync"], check=True)
    try:
        with open("/proc/sys/vm/drop_caches", "w") as f:
            f.write("3\n")
        return True
    except OSError as e:
        log(f"cannot drop the page cache ({e}): the cold run is not cold (run as root)")
        return False


def read_through(dirs):
    """Warm page cache: every input file read once."""
    for d in dirs:
        for root, _, files in os.walk(d):
            for f in files:
                with open(os.path.join(root, f), "rb") as fh:
                    while fh.read(1 << 24):
                        pass


def proc_numbers(pid):
    """RSS (KiB), CPU seconds (user + system) and /proc/PID/io of a live process, or None."""
    try:
        status = open(f"/proc/{pid}/status").read()
        stat = open(f"/proc/{pid}/stat").read()
        io = open(f"/proc/{pid}/io").read()
    except OSError:
        return None
    rss = 0
    for line in status.splitlines():
        if line.startswith("VmRSS:"):
            rss = int(line.split()[1])
    fields = stat.rsplit(")", 1)[1].split()
    tick = os.sysconf("SC_CLK_TCK")
    cpu = (int(fields[11]) + int(fields[12])) / tick
    ion = {k: int(v) for k, v in (line.split(": ") for line in io.splitlines() if ": " in line)}
    return {"rss_kib": rss, "cpu_s": cpu, "io": ion}


def child_of(pid):
    try:
        kids = open(f"/proc/{pid}/task/{pid}/children").read().split()
        return int(kids[0]) if kids else None
    except OSError:
        return None


STAGE_OF_PREFIX = {"register": "register", "mask": "pass", "labels": "pass", "pack": "pack",
                   "vdb": "vdb"}


def run_monitored(cmd, time_log, out_log, watch_dir, keep_free):
    """Runs cmd under /usr/bin/time -v; samples the child (RSS, CPU, io) every SAMPLE_S and
    attributes the samples to the stage of the last progress line. Returns (time -v numbers,
    per-stage dict, last io, load samples)."""
    proc = subprocess.Popen(["/usr/bin/time", "-v", "-o", time_log] + cmd,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            bufsize=1)
    # vispack-run starts with register (whose first progress line comes after its first pair).
    state = {"stage": "register", "stages": {}, "io": {}, "load": [], "disk_full": None}
    lock = threading.Lock()
    start = time.time()

    def reader():
        with open(out_log, "w") as out:
            for line in proc.stdout:
                out.write(line)
                word = line.split(":", 1)[0].strip()
                if word in STAGE_OF_PREFIX and ("slices" in line or "exporting" in line):
                    with lock:
                        state["stage"] = STAGE_OF_PREFIX[word]

    t = threading.Thread(target=reader, daemon=True)
    t.start()
    child = None
    last_load = 0.0
    while proc.poll() is None:
        time.sleep(SAMPLE_S)
        child = child or child_of(proc.pid)
        if not child:
            continue
        n = proc_numbers(child)
        if not n:
            continue
        now = time.time()
        with lock:
            st = state["stages"].setdefault(state["stage"], {
                "first_s": now - start, "cpu_first": n["cpu_s"], "io_first": n["io"],
                "peak_rss_kib": 0})
            st["last_s"] = now - start
            st["cpu_last"] = n["cpu_s"]
            st["io_last"] = n["io"]
            st["peak_rss_kib"] = max(st["peak_rss_kib"], n["rss_kib"])
            state["io"] = n["io"]
        if now - last_load >= 5:
            state["load"].append(os.getloadavg()[0])
            last_load = now
        if free_bytes(watch_dir) < keep_free:
            state["disk_full"] = (f"free space in {watch_dir} fell under {keep_free / 1e9:.0f} GB "
                                  f"({free_bytes(watch_dir) / 1e9:.1f} GB) during the run: killed it")
            os.kill(child, signal.SIGTERM)
    t.join()
    if state["disk_full"]:
        raise DiskFull(state["disk_full"])
    if proc.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed (exit {proc.returncode}); log: {out_log}")
    return read_time_v(time_log), state


def stage_rows(stages):
    """Per stage: wall (first to last sample), CPU, peak sampled RSS, bytes read/written. A stage
    runs from its first sample to the next stage's first sample."""
    names = [n for n in ("register", "pass", "pack", "vdb") if n in stages]
    rows = []
    for i, name in enumerate(names):
        st = stages[name]
        nxt = stages[names[i + 1]] if i + 1 < len(names) else None
        end_s = nxt["first_s"] if nxt else st["last_s"]
        cpu_end = nxt["cpu_first"] if nxt else st["cpu_last"]
        io_end = nxt["io_first"] if nxt else st["io_last"]
        rows.append({"stage": name, "wall_s": round(end_s - st["first_s"], 2),
                     "cpu_s": round(cpu_end - st["cpu_first"], 2),
                     "peak_rss_mib": round(st["peak_rss_kib"] / 1024, 1),
                     "read_bytes": io_end.get("read_bytes", 0) - st["io_first"].get("read_bytes", 0),
                     "rchar": io_end.get("rchar", 0) - st["io_first"].get("rchar", 0),
                     "write_bytes": io_end.get("write_bytes", 0) - st["io_first"].get("write_bytes", 0)})
    return rows


def truth_every(args, slices):
    """--truth-every, or by default about 30 sampled truth slices (every 64th of the male)."""
    return args.truth_every or max(2, min(64, slices // 29))


def generator_command(args, name, preset, slices, extra):
    return [args.generator or os.path.join(args.bin, "vispack-phantom"), "--out", os.path.join(args.work, name),
            "--preset", preset, "--slices", str(slices), "--rgb-raw", "--truth-every",
            str(truth_every(args, slices)), "--seed", "1", "--threads", "2", "--quiet",
            "--keep-free-gb", str(args.keep_free_gb)] + extra


def write_stamp(folder, cmd, tv, date, load0):
    """stack.json: how the stack was made (the key a later run compares) and what it cost."""
    info = {"key": {"args": cmd[1:], "generator_sha256": sha256(cmd[0])}, "date": date,
            "command": " ".join(["vispack-phantom"] + cmd[1:]), "generate": tv,
            "load_before": load0, "load_after": os.getloadavg(),
            "bytes": {d: du(os.path.join(folder, d)) for d in ("rgb", "ct", "seg", "truth")}}
    stamp = os.path.join(folder, "stack.json")
    with open(stamp + ".tmp", "w") as f:
        json.dump(info, f, indent=1)
    os.replace(stamp + ".tmp", stamp)
    return info


def generate(args, name, preset, slices, extra):
    """The stack folder, generated unless one made by the same generator binary with the same
    arguments is there (its stack.json says so)."""
    folder = os.path.join(args.work, name)
    cmd = generator_command(args, name, preset, slices, extra)
    stamp = os.path.join(folder, "stack.json")
    if os.path.exists(stamp):
        old = json.load(open(stamp))
        if old.get("key") == {"args": cmd[1:], "generator_sha256": sha256(cmd[0])}:
            log(f"{name}: reusing the stack generated {old.get('date', '?')}")
            return folder, old
    shutil.rmtree(folder, ignore_errors=True)
    os.makedirs(args.work, exist_ok=True)
    log(f"{name}: generating {slices} slices ({preset})")
    load0 = os.getloadavg()
    date = time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())
    tv = read_time_v_run(cmd, os.path.join(args.results, f"{name}-generate.time"))
    info = write_stamp(folder, cmd, tv, date, load0)
    log(f"{name}: generated in {tv['wall_s']} s, {tv['cpu_s']:.0f} CPU-s, peak "
        f"{tv['peak_rss_mib']:.0f} MiB")
    return folder, info


def read_time_v_run(cmd, time_log):
    r = subprocess.run(["/usr/bin/time", "-v", "-o", time_log] + cmd, stdout=subprocess.PIPE,
                       stderr=subprocess.STDOUT, text=True)
    if r.returncode != 0 and ": needs about " in r.stdout:
        raise DiskFull(r.stdout.strip().splitlines()[-1])  # the generator's free-space check
    if r.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed (exit {r.returncode}): {r.stdout.strip()[-600:]}")
    return read_time_v(time_log)


def run_once(args, name, folder, pixels_per_slice, slices, cold):
    mode = "cold" if cold else "warm"
    for sub in ("work", "out"):
        shutil.rmtree(os.path.join(folder, sub), ignore_errors=True)
    need_space(args.work, int(RUN_BYTES_PER_PIXEL * pixels_per_slice * slices),
               args.keep_free_gb * 1e9, f"{name} {mode} run")
    if cold:
        dropped = drop_caches()
    else:
        dropped = False
        t0 = time.time()
        read_through([os.path.join(folder, d) for d in ("rgb", "ct", "seg")])
        log(f"{name}: inputs read once for the warm run ({time.time() - t0:.1f} s)")
    log(f"{name}: vispack-run, {mode} page cache")
    load0 = os.getloadavg()
    tv, state = run_monitored(
        [os.path.join(args.bin, "vispack-run"), os.path.join(folder, "config.json"), "--threads", "2"],
        os.path.join(args.results, f"{name}-{mode}.time"),
        os.path.join(args.results, f"{name}-{mode}.log"), args.work, args.keep_free_gb * 1e9)
    time_log = open(os.path.join(args.results, f"{name}-{mode}.time")).read()
    blocks = {}
    for key in ("File system inputs", "File system outputs"):
        for line in time_log.splitlines():
            if key in line:
                blocks[key] = int(line.split(":")[1]) * 512
    reports = {}
    for stage in ("register", "mask", "labels", "pack", "vdb"):
        p = os.path.join(folder, "work", stage, "report.json")
        if os.path.exists(p):
            r = json.load(open(p))
            reports[stage] = {k: r.get(k) for k in ("seconds", "level", "level_choice",
                                                    "max_memory_mb", "peak_rss_mb", "output_bytes",
                                                    "estimates")}
    out = os.path.join(folder, "out")
    row = {"mode": mode, "page_cache_dropped": dropped, "time_v": tv,
           "read_bytes_storage": blocks.get("File system inputs"),
           "written_bytes_storage": blocks.get("File system outputs"),
           "io_last_sample": state["io"], "stages": stage_rows(state["stages"]),
           "stage_reports": reports, "load_before": load0, "load_after": os.getloadavg(),
           "load_samples": state["load"],
           "bytes": {"work": du(os.path.join(folder, "work")),
                     "vpk": os.path.getsize(os.path.join(out, "volume.vpk")),
                     "vdb": os.path.getsize(os.path.join(out, "volume.vdb"))
                     if os.path.exists(os.path.join(out, "volume.vdb")) else None}}
    log(f"{name} {mode}: {tv['wall_s']} s wall, {tv['cpu_s']:.0f} CPU-s "
        f"({tv['cpu_s'] / slices:.3f}/slice), peak {tv['peak_rss_mib']:.0f} MiB, load "
        f"{load0[0]:.1f}->{row['load_after'][0]:.1f}")
    return row


def score(args, folder):
    r = subprocess.run([os.path.join(args.bin, "vispack-score"), "--truth",
                        os.path.join(folder, "truth"), "--work", os.path.join(folder, "work"),
                        "--json"], capture_output=True, text=True)
    if r.returncode != 0:
        return {"error": r.stderr.strip()[-400:]}
    s = json.loads(r.stdout)
    out = {"truth_sample": len(s.get("truth_sample", [])),
           "drift_rms_px": s["drift"]["rms_px"], "drift_max_px": s["drift"]["max_px"],
           "over_body_rms_px": s["drift"]["over_body_rms_px"],
           "over_body_max_px": s["drift"]["over_body_max_px"],
           "jumps": {k: s["jumps"][k] for k in ("true", "found", "missed", "false")}}
    if "mask" in s:
        out["mask_mean_body_iou"] = s["mask"]["mean_body_iou"]
        out["mask_min_body_iou"] = s["mask"]["min_body_iou"]
    if "labels" in s:
        out["labels_accuracy"] = s["labels"]["accuracy"]
    return out


def bench_stack(args, name, preset, slices, extra, width, height, out, save, ct_every=1):
    """Generates, runs and scores one stack; its row is in out["stacks"] from the start and saved
    after every run, so a run stopped later keeps what was measured."""
    row = {"name": name, "preset": preset, "slices": slices, "width": width, "height": height,
           "runs": []}
    if ct_every > 1:
        row["ct_every"] = ct_every
    out["stacks"].append(row)
    folder = os.path.join(args.work, name)
    modes = [False] if args.no_cold else [True, False]
    if args.warm_first:
        modes.reverse()
    try:
        folder, row["generate"] = generate(args, name, preset, slices, extra)
        save()
        if args.generate_only:
            return row
        for cold in modes:
            row["runs"].append(run_once(args, name, folder, width * height, slices, cold))
            save()
        row["score"] = score(args, folder)
        log(f"{name}: score {json.dumps(row['score'])}")
    except RuntimeError as e:
        row["error"] = str(e)
        log(f"{name}: {e}")
    finally:
        if not args.keep_stacks and not args.generate_only:
            shutil.rmtree(folder, ignore_errors=True)
            log(f"{name}: stack deleted")
    return row


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--bin", required=True)
    ap.add_argument("--work", required=True)
    ap.add_argument("--results", required=True)
    ap.add_argument("--slices", default="128 512 1871")
    ap.add_argument("--korean", type=int, default=64, help="slices of the Korean-sized stack (0: none)")
    ap.add_argument("--female", type=int, default=1500,
                    help="colour slices of the female-shaped stack, a CT slice at every third (0: none)")
    ap.add_argument("--truth-every", type=int, default=0,
                    help="truth sample step (default: about 30 slices, at most every 64th)")
    ap.add_argument("--keep-free-gb", type=float, default=10)
    ap.add_argument("--keep-stacks", action="store_true")
    ap.add_argument("--generator", default="",
                    help="the vispack-phantom binary that makes the stacks (default: BIN's); a stack is "
                         "reused only if made by the same binary with the same arguments")
    ap.add_argument("--generate-only", action="store_true",
                    help="make (or find) the stacks and stop: no runs, the stacks kept")
    ap.add_argument("--no-cold", action="store_true")
    ap.add_argument("--warm-first", action="store_true",
                    help="the warm run first (after reading the inputs once), then the cold one")
    args = ap.parse_args()
    args.work, args.results = os.path.abspath(args.work), os.path.abspath(args.results)
    os.makedirs(args.results, exist_ok=True)
    os.makedirs(args.work, exist_ok=True)
    out = {"machine": dict(machine.provenance(), date=time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
                           cores=os.cpu_count(), load_start=os.getloadavg()),
           "truth_every": args.truth_every or "about 30 slices", "keep_free_gb": args.keep_free_gb, "stacks": []}
    path = os.path.join(args.results, "full_length.json")

    def save():
        with open(path + ".tmp", "w") as f:
            json.dump(out, f, indent=1)
        os.replace(path + ".tmp", path)

    # The male's artefacts: four blocks, twelve black slices (fewer on a short test stack).
    def male(n):
        return ["--blocks", "4", "--black-slices", str(min(12, max(1, n // 8)))]
    plan = [(f"male-{n}", "male", int(n), male(int(n)), 2048, 1216, 1) for n in args.slices.split()]
    if args.female:
        plan.append((f"female-{args.female}", "male", args.female,
                     male(args.female) + ["--ct-every", "3"], 2048, 1216, 3))
    if args.korean:
        plan.append((f"korean-{args.korean}", "korean", args.korean,
                     ["--blocks", "4", "--black-slices", "3"], 4368, 2912, 1))
    try:
        for name, preset, n, extra, w, h, ct_every in plan:
            bench_stack(args, name, preset, n, extra, w, h, out, save, ct_every)
            save()
    except DiskFull as e:
        out["stopped"] = str(e)
        save()
        print(f"full_length: {e}", file=sys.stderr)
        return 1
    out["machine"]["load_end"] = os.getloadavg()
    out["machine"]["date_end"] = time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())
    save()
    log(f"wrote {path}")
    return 1 if any("error" in s for s in out["stacks"]) else 0


if __name__ == "__main__":
    sys.exit(main())
