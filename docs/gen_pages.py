"""The documentation pages made at build time (run by mkdocs-gen-files).

The benchmarks pages are generated from `benchmarks/results/*.json`, so that no measured
number is ever copied by hand: each results file becomes a section with the machine and
date of its run, its settings, and a table for every list of records it holds; the
figures the benchmark scripts saved beside their results (`NAME.png` for `NAME.json`)
are shown with them; work-precision and scaling files without one get a plot drawn here
from their records. Every results file appears on exactly one page (`FAMILIES`; a file
that fits none lands on "Other results").

Run as `python docs/gen_pages.py --write OUT_DIR` it writes the pages into OUT_DIR
instead, for a look without mkdocs.
"""

import glob
import io
import json
import math
import os
import re
import sys

HERE = os.path.dirname(os.path.abspath(__file__))
RESULTS = os.path.join(HERE, os.pardir, "benchmarks", "results")

# page -> (title, introduction, file-name patterns); the first page that matches wins.
FAMILIES = [
    ("work-precision", "Work against precision",
     "Run time against error on the paper's 2D L-shape (`benchmarks/work_precision.py`): every jaxvisco time "
     "element at constant steps and with error control, against scipy's Radau and BDF and diffrax's solvers on the "
     "same semi-discrete ODE (`jaxvisco.semidiscrete`, lumped mass for every method). The error is measured at "
     "the end time against a reference run; `wall_s` excludes compilation.",
     [r"work_precision.*"]),
    ("adaptive-steps", "Error-controlled steps",
     "`PIDController` runs: how the estimate compares with the true local error (effectivity), how the errors "
     "follow the tolerance (proportionality), and how many steps the adaptive runs take against the constant "
     "step of the same accuracy, on the paper's free L-shape and on a clamped L-shape that comes to rest.",
     [r"adaptive_.*", r"controller_coefficients"]),
    ("scaling", "Large meshes",
     "The 3D L-shape (hex8, tet4) by refinement (`benchmarks/scaling.py`): milliseconds per step, iterations, peak "
     "memory and compile time, on the sparse LU and on the multigrid path, on CPU and on one GPU.",
     [r"scaling.*", r"switch_.*", r"cycles_.*"]),
    ("startup-and-compile", "Start-up and compilation",
     "The first call of a fresh process (tracing and compiling the time loop), the same with the compilation "
     "cache filled, `jaxvisco paper --quick` cold and cached (`benchmarks/startup.py`), what the compiled "
     "program is made of (`benchmarks/compile_cost.py`), and a fit's whole processes, cold and cached "
     "(`benchmarks/identify_startup.py`).",
     [r"startup.*", r"compile_cost", r"identify_startup"]),
    ("cost-per-step", "Cost of a step",
     "A step in residual evaluations (`benchmarks/step_cost.py`), the share of the host sparse LU "
     "(`profile_step.py`), the chord iterations' rate (`chord_rate.py`), saving and the internal variable "
     "(`skip_cost.py`), batches of runs (`batch_cost.py`) and gradients (`gradients.py`).",
     [r"step_cost.*", r"profile_step.*", r"chord_rate", r"skip_cost", r"batch_cost", r"gradients"]),
    ("robustness", "Large steps and robustness",
     "Every scheme at every step size to t = 100 with three material variants (`benchmarks/stability.py`), the "
     "paper scene at h = 1 (`large_steps.py`), the rule that gives up a stalled Newton solve "
     "(`stall_limit.py`), and why eG(2) cannot take the paper's h = 1 step (`eg2_large_step.py`, "
     "`eg2_arclength.py`, `eg2_h_continuation.py`).",
     [r"stability", r"large_steps", r"stall_limit", r"eg2_.*"]),
    ("revisions", "Revision comparisons",
     "A/B measurements of code changes (`benchmarks/revision_cost.py --base REV`): the same case in fresh "
     "processes, the two trees alternating every round.",
     [r"revision_cost", r"rc_.*", r"session16_.*", r"einsum_cost", r"defect_cost", r"cycles_s26"]),
]
MAX_ROWS = 150  # longer record lists are shown in part (the file holds them all)


# ------------------------------------------------------------------ formatting
def fmt(v):
    """One value as table text: numbers to four significant digits."""
    if v is None:
        return "–"
    if isinstance(v, bool):
        return "yes" if v else "no"
    if isinstance(v, int):
        return f"{v:,}".replace(",", " ") if abs(v) >= 10000 else str(v)
    if isinstance(v, float):
        if math.isnan(v):
            return "nan"
        if math.isinf(v):
            return "inf" if v > 0 else "-inf"
        if v == 0:
            return "0"
        a = abs(v)
        return f"{v:.4g}" if 1e-3 <= a < 1e6 else f"{v:.3e}"
    if isinstance(v, (list, tuple)):
        if len(v) <= 8 and all(not isinstance(a, (list, dict)) for a in v):
            return ", ".join(fmt(a) for a in v)
        return f"({len(v)} values)"
    if isinstance(v, dict):
        return "; ".join(f"{k}: {fmt(x)}" for k, x in v.items()) if len(v) <= 4 else f"({len(v)} entries)"
    return str(v).replace("|", "\\|").replace("\n", " ")


def flat(d, prefix="", depth=2):
    """A dict flattened to `a.b` keys (`depth` levels)."""
    out = {}
    for k, v in d.items():
        key = f"{prefix}{k}"
        if isinstance(v, dict) and depth > 1:
            out.update(flat(v, key + ".", depth - 1))
        else:
            out[key] = v
    return out


def table(rows, columns=None):
    """A markdown table of records (dicts)."""
    rows = [flat(r) for r in rows]
    if columns is None:
        columns = []
        for r in rows:
            for k, v in r.items():
                if k not in columns and not (isinstance(v, (list, dict)) and len(v) > 8):
                    columns.append(k)
    lines = ["| " + " | ".join(columns) + " |", "|" + "---|" * len(columns)]
    for r in rows[:MAX_ROWS]:
        lines.append("| " + " | ".join(fmt(r.get(c)) for c in columns) + " |")
    if len(rows) > MAX_ROWS:
        lines.append(f"\n*The first {MAX_ROWS} of {len(rows)} records; the file holds all of them.*")
    return "\n".join(lines)


def key_values(d):
    return table([{"key": k, "value": v} for k, v in flat(d).items()], ["key", "value"])


def is_records(v):
    return isinstance(v, list) and v and all(isinstance(r, dict) for r in v)


# ------------------------------------------------------------------ one results file
def machine_line(d):
    m = d.get("machine")
    if isinstance(m, dict):
        cpu = m.get("cpu_model") or m.get("cpu") or "?"
        parts = [f"{cpu}, {m.get('cores', '?')} cores", f"measured {m.get('date') or d.get('date') or '?'}"]
        if m.get("jax"):
            parts.append(f"jax {m['jax']}")
        load = m.get("load_average_at_start")
        if load:
            parts.append(f"load at start {fmt(load[0])}")
        return "; ".join(parts) + "."
    if isinstance(m, str):
        return m
    return f"measured {d.get('date', '?')}." if d.get("date") else ""


def section(name, d, figures):
    """The markdown of one results file."""
    out = [f"## `{name}` {{ #{slug(name)} }}", ""]
    out.append(f"Source: `benchmarks/results/{name}.json`. {machine_line(d)}")
    for key in ("what", "case", "how", "command", "timing", "note", "scene"):
        if isinstance(d.get(key), str):
            out += ["", f"**{key}:** {fmt(d[key])}"]
    out.append("")
    if isinstance(d.get("settings"), dict):
        out += ["??? note \"Settings\"", "", indent(key_values(d["settings"])), ""]
    elif isinstance(d.get("settings"), str):
        out += [f"**settings:** {fmt(d['settings'])}", ""]
    for fig in figures:
        out += [f"![{name}]({fig})", ""]
    for key, v in d.items():
        if key in ("machine", "settings", "what", "case", "how", "command", "timing", "note", "scene", "date"):
            continue
        if is_records(v):
            out += [f"**{key}** ({len(v)} records)", "", table(v), ""]
        elif isinstance(v, dict) and v and all(is_records(x.get("rows")) if isinstance(x, dict) else False
                                             for x in v.values()):
            for sub, x in v.items():
                out += [f"**{key}: {sub}**", "", table(x["rows"]), ""]
        elif isinstance(v, dict) and v:
            if key == "scenes":
                out += scenes_section(v)
            else:
                out += [f"**{key}**", "", key_values(v), ""]
        elif not isinstance(v, (list, dict)):
            out += [f"**{key}:** {fmt(v)}", ""]
    return "\n".join(out)


def scenes_section(scenes):
    """Work-precision files: per scene, the runs and the time at the target error."""
    out = []
    for scene, s in scenes.items():
        out += [f"**{scene}** ({fmt(s.get('dofs'))} unknowns)", ""]
        if isinstance(s.get("wall_at_target_s"), dict):
            best = s.get("best_jaxvisco")
            rows = [{"method": m, "wall at target error (s)": w,
                     "speed-up of the best jaxvisco scheme": (s.get("speedup_at_target") or {}).get(m)}
                    for m, w in s["wall_at_target_s"].items()]
            out += [f"Wall time at the target error (best jaxvisco scheme: {fmt(best)}):", "", table(rows), ""]
        if is_records(s.get("runs")):
            cols = ["method", "h", "rtol", "steps", "status", "error", "error_x", "error_H", "error_D", "wall_s",
                    "compile_s", "newton_per_step"]
            present = [c for c in cols if any(c in r for r in s["runs"])]
            out += ["??? note \"Every run\"", "", indent(table(s["runs"], present)), ""]
    return out


def indent(text):
    return "\n".join("    " + line if line else "" for line in text.splitlines())


def slug(name):
    return re.sub(r"[^a-z0-9]+", "-", name.lower()).strip("-")


# ------------------------------------------------------------------ plots from the records
def work_precision_plot(d):
    """Error against wall time, one curve per method (every scene of the file)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    scenes = d.get("scenes") or {}
    fig, axes = plt.subplots(1, len(scenes), figsize=(6.4 * len(scenes), 4.4), squeeze=False)
    drawn = False
    for ax, (scene, s) in zip(axes[0], scenes.items()):
        by = {}
        for r in s.get("runs") or []:
            e, w = r.get("error"), r.get("wall_s")
            if isinstance(e, (int, float)) and isinstance(w, (int, float)) and e > 0 and w > 0 and \
                    r.get("status", "done") in ("done", "success", True):
                by.setdefault(r.get("method", "?"), []).append((w, e))
        for method, pts in sorted(by.items()):
            pts.sort()
            ax.loglog([p[0] for p in pts], [p[1] for p in pts], "o-" if "eG" in method else ".--", ms=3,
                      label=method)
            drawn = True
        ax.set_xlabel("wall time (s, after compilation)")
        ax.set_ylabel("error at the end time")
        ax.set_title(scene)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=6, ncol=2)
    return _png(fig) if drawn else None


def scaling_plot(d):
    """Milliseconds per step against unknowns, one curve per element and preconditioner."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    by = {}
    for r in d.get("rows") or []:
        ms, n = r.get("ms_per_step"), r.get("dofs")
        if isinstance(ms, (int, float)) and isinstance(n, (int, float)) and ms > 0:
            by.setdefault(f"{r.get('element', '?')} {r.get('preconditioner', '')}".strip(), []).append((n, ms))
    if not by:
        return None
    fig, ax = plt.subplots(figsize=(6.4, 4.4))
    for label, pts in sorted(by.items()):
        pts.sort()
        ax.loglog([p[0] for p in pts], [p[1] for p in pts], "o-", ms=3, label=label)
    ax.set_xlabel("position unknowns")
    ax.set_ylabel("ms per step")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7)
    return _png(fig)


def _png(fig):
    import matplotlib.pyplot as plt

    buf = io.BytesIO()
    fig.tight_layout()
    fig.savefig(buf, format="png", dpi=90)
    plt.close(fig)
    return buf.getvalue()


# ------------------------------------------------------------------ the pages
def family_of(name):
    for page, _, _, patterns in FAMILIES:
        if any(re.fullmatch(p, name) for p in patterns):
            return page
    return "other"


def summary_page(results):
    """The landing page: the targets of the performance issues, from `summary.json`."""
    s = results.get("summary", {})
    out = ["# Benchmarks", "",
           "Every number on these pages is read from `benchmarks/results/*.json` when the documentation is built; "
           "the files record the machine, the date, the load and the settings of each run, and the scripts that "
           "write them are in `benchmarks/` (see [the scripts and their measurement log](running.md)). Identical runs on the "
           "shared 2-core machines vary by up to about 1.4 times over minutes, so the files give medians of "
           "repeats or alternating pairs. [Performance notes](notes.md) explains what the numbers mean for the "
           "design.", ""]
    if s:
        out += [f"Summary from `benchmarks/results/summary.json` ({machine_line(s)})", ""]
        for key, title in (("targets", "Targets of issue #6"), ("issue_16_targets", "Targets of issue #16")):
            t = s.get(key)
            if isinstance(t, dict):
                rows = []
                for target, v in t.items():
                    if isinstance(v, dict):
                        detail = {k: x for k, x in v.items() if k not in ("met", "target")}
                        rows.append({"target": target, "met": v.get("met"), "measured": detail})
                    else:
                        rows.append({"target": target, "met": None, "measured": v})
                out += [f"## {title}", "", _targets_table(rows), ""]
    out += ["## Pages", ""]
    for page, title, intro, _ in FAMILIES:
        out.append(f"- [{title}]({page}.md): {intro.split('. ')[0].rstrip('.')}.")
    out.append("- [Other results](other.md)")
    return "\n".join(out) + "\n"


def _targets_table(rows):
    lines = ["| target | met | measured |", "|---|---|---|"]
    for r in rows:
        m = r["measured"]
        text = "; ".join(f"{k}: {fmt(v)}" for k, v in flat(m).items()) if isinstance(m, dict) else fmt(m)
        lines.append(f"| {fmt(r['target'])} | {fmt(r['met'])} | {text.replace('|', '/')} |")
    return "\n".join(lines)


def pages():
    """{path: bytes or str} of every generated page and figure."""
    results = {}
    for path in sorted(glob.glob(os.path.join(RESULTS, "*.json"))):
        with open(path, encoding="utf-8") as f:
            results[os.path.splitext(os.path.basename(path))[0]] = json.load(f)
    out = {"benchmarks/index.md": summary_page(results)}
    groups = {}
    for name in results:
        if name != "summary":
            groups.setdefault(family_of(name), []).append(name)
    titles = {page: (title, intro) for page, title, intro, _ in FAMILIES}
    titles["other"] = ("Other results", "Results files that fit none of the other pages.")
    for page, (title, intro) in titles.items():
        names = groups.get(page, [])
        body = [f"# {title}", "", intro, ""]
        if names:
            body += ["Results files on this page: " + ", ".join(f"[`{n}`](#{slug(n)})" for n in names) + ".", ""]
        else:
            body += ["(None at present.)", ""]
        for name in names:
            d = results[name]
            figs = []
            script_png = os.path.join(RESULTS, name + ".png")
            if os.path.exists(script_png):  # drawn by the benchmark script from the same records
                with open(script_png, "rb") as f:
                    out[f"benchmarks/figures/{name}.png"] = f.read()
                figs.append(f"figures/{name}.png")
            else:
                made = None
                if name.startswith("work_precision"):
                    made = work_precision_plot(d)
                elif name.startswith("scaling") or name.startswith("switch"):
                    made = scaling_plot(d)
                if made is not None:
                    out[f"benchmarks/figures/{name}.gen.png"] = made
                    figs.append(f"figures/{name}.gen.png")
            body += [section(name, d, figs), ""]
        out[f"benchmarks/{page}.md"] = "\n".join(body)
    return out


def _write_with_mkdocs():
    import mkdocs_gen_files

    for path, content in pages().items():
        with mkdocs_gen_files.open(path, "wb" if isinstance(content, bytes) else "w") as f:
            f.write(content)


if __name__ == "__main__" and sys.argv[1:2] == ["--write"]:
    target = sys.argv[2]
    for path, content in pages().items():
        full = os.path.join(target, path)
        os.makedirs(os.path.dirname(full), exist_ok=True)
        with open(full, "wb" if isinstance(content, bytes) else "w") as f:
            f.write(content)
else:
    _write_with_mkdocs()
