"""Every code block of the README, the documentation pages and the docstrings the API
pages render runs (issue #61), so that the documentation cannot rot:

- `python` blocks run, those of one page in order in one namespace (docstrings: each
  object's blocks on their own);
- `bash` blocks run: those of `jaxvisco` commands alone through the command line's `main`
  in this process, others in bash with `jaxvisco` the command line of the jaxvisco under
  test;
- `toml` blocks parse, and those that are scene files (with a `[mesh]`) are read as such;
  `yaml` blocks parse;
- a block preceded by `<!-- skip: why -->` does not run (install commands, long runs,
  example output); the reason is required. A `python` block that includes an example
  script (`--8<-- "examples/NAME.py"`) is run by `tests/test_examples.py` (the gallery).

Every page runs in a scratch folder with copies of `examples/data`, `examples/scenes` and
`examples/fit`.
The examples share programs on purpose (the paper's L-shape, eG(1), h = 0.1, up to 8
steps), so that the whole file compiles a few programs.
"""

import contextlib
import inspect
import io
import os
import re
import shlex
import shutil
import subprocess
import sys
import textwrap

import jax
import pytest
from helpers import default_optimization_env, subprocess_env

ROOT = os.path.abspath(os.path.join(os.path.dirname(__file__), os.pardir))
SNIPPET = re.compile(r'^(\s*)--8<-- "([^"]+)"\s*$', re.M)
FENCE = re.compile(r"^(?P<indent>[ \t]*)```(?P<lang>[\w-]*)[^\n]*\n(?P<body>.*?)^(?P=indent)```[ \t]*$",
                   re.M | re.S)
SKIP = re.compile(r"<!--\s*skip:\s*(?P<why>[^>]*?)\s*-->\s*$")


def expand(text, seen=()):
    """`text` with pymdownx.snippets' `--8<-- "path"` lines replaced by the files (paths
    from the repository root, as `mkdocs.yml` sets `base_path`), indented as the line."""
    def one(m):
        path = m.group(2)
        assert path not in seen, f"snippet loop at {path}"
        with open(os.path.join(ROOT, path), encoding="utf-8") as f:
            body = expand(f.read(), seen + (path,))
        return textwrap.indent(body.rstrip("\n"), m.group(1))
    return SNIPPET.sub(one, text)


def blocks(text):
    """`(lang, body, skip_reason, include)` of every fenced block of a Markdown text,
    snippets expanded; `include` is the example script a `python` block consists of
    (`--8<-- "examples/NAME.py"`), which is not expanded but named."""
    def mark(m):
        inc = SNIPPET.fullmatch(textwrap.dedent(m.group("body")).strip())
        if m.group("lang") == "python" and inc and inc.group(2).startswith("examples/"):
            return m.group(0).replace(m.group("body"), f"{m.group('indent')}# include {inc.group(2)}\n")
        return m.group(0)

    text = expand(FENCE.sub(mark, text))
    out = []
    for m in FENCE.finditer(text):
        before = text[:m.start()].rstrip("\n").splitlines()
        skip = SKIP.match(before[-1].strip()) if before else None
        body = textwrap.dedent(m.group("body"))
        inc = re.fullmatch(r"# include (\S+)\n?", body)
        out.append((m.group("lang"), body, skip.group("why") if skip else None, inc.group(1) if inc else None))
    return out


def pages():
    out = ["README.md"]
    for d, _, files in os.walk(os.path.join(ROOT, "docs")):
        out += [os.path.relpath(os.path.join(d, f), ROOT) for f in files if f.endswith(".md")]
    return sorted(out)


@pytest.fixture
def scratch(tmp_path, monkeypatch):
    """A scratch folder with the example data, scenes and fit files, as the current
    directory; JAX's cache settings restored afterwards (a page may turn on a cache of
    its own)."""
    for sub in ("data", "scenes", "fit"):
        shutil.copytree(os.path.join(ROOT, "examples", sub), tmp_path / "examples" / sub)
    monkeypatch.chdir(tmp_path)
    keep = {k: getattr(jax.config, k) for k in ("jax_compilation_cache_dir", "jax_persistent_cache_min_compile_time_secs")}
    import matplotlib

    matplotlib.use("Agg")
    yield tmp_path
    for k, v in keep.items():
        jax.config.update(k, v)


def shim(folder):
    """A `jaxvisco` command on PATH that runs this interpreter's jaxvisco."""
    os.makedirs(folder, exist_ok=True)
    path = os.path.join(folder, "jaxvisco")
    with open(path, "w") as f:
        f.write(f'#!/bin/sh\nexec "{sys.executable}" -m jaxvisco.cli "$@"\n')
    os.chmod(path, 0o755)
    return folder


def run_block(lang, body, where, namespace, folder, include=None):
    if lang == "python":
        if include is not None:
            from test_examples import GALLERY_NAMES

            name = os.path.splitext(os.path.basename(include))[0]
            assert include.startswith("examples/") and name in GALLERY_NAMES, \
                f"{where}: {include} is shown but not run by tests/test_examples.py"
            return
        exec(compile(body, where, "exec"), namespace)
    elif lang == "bash" and all(line.startswith("jaxvisco ") for line in body.strip().splitlines()):
        for line in body.strip().splitlines():
            run_command(line, where, folder)
    elif lang == "bash":
        env = subprocess_env()
        env["PATH"] = shim(str(folder / ".bin")) + os.pathsep + env["PATH"]
        env["PYTHONPATH"] = os.pathsep.join([ROOT] + [p for p in sys.path if p])
        p = subprocess.run(["bash", "-e", "-c", body], cwd=folder, env=env, capture_output=True, text=True,
                           timeout=600)
        assert p.returncode == 0, f"{where}:\n{body}\n{p.stderr[-3000:]}"
    elif lang == "toml":
        from jaxvisco._scenefile._scenefile import read_quietly, tomllib

        doc = tomllib.loads(body)
        if "mesh" in doc:
            read_quietly(where, source=body, base_dir=os.path.join(folder, "examples", "scenes"))
    elif lang == "yaml":
        import yaml

        yaml.safe_load(body)
    else:
        raise AssertionError(f"{where}: a ```{lang or '(no language)'} block runs nowhere; mark it "
                             "<!-- skip: why --> or give it a language that runs")


def run_command(line, where, folder):
    """One `jaxvisco ...` line (with an optional `> FILE`), in this process: the command's
    `main`, as the console script calls it (no interpreter start-up per line)."""
    from jaxvisco.cli import main

    argv = shlex.split(line)[1:]
    out = None
    if ">" in argv:
        i = argv.index(">")
        argv, out = argv[:i], folder / argv[i + 1]
    buf = io.StringIO()
    try:
        with contextlib.redirect_stdout(buf):
            code = main(argv)
    except SystemExit as e:  # --version, --help
        code = e.code
    assert code == 0, f"{where}: `{line}` exited with {code}"
    if out is not None:
        out.write_text(buf.getvalue())


# Pages whose code runs its compiled programs far more often than it compiles them (fits:
# dozens of runs with their tangents). They run in a subprocess with XLA's default
# optimization instead of the suite's cheap-compile flags (conftest.py), under which the
# identification guide took 230 s instead of 126 s.
RUN_BOUND = ("docs/guide/identification.md",)


def run_page(page, folder):
    """Every block of `page` in order, in one namespace, in `folder` (the current directory)."""
    with open(os.path.join(ROOT, page), encoding="utf-8") as f:
        text = f.read()
    namespace = {"__name__": "__doc_example__"}
    for i, (lang, body, skip, include) in enumerate(blocks(text)):
        where = f"{page}, block {i + 1}"
        if skip is not None:
            assert skip.strip(), f"{where}: a skipped block needs its reason"
            continue
        with contextlib.redirect_stdout(open(os.devnull, "w")):
            run_block(lang, body, where, namespace, folder, include)


@pytest.mark.timeout(900)
@pytest.mark.parametrize("page", pages())
def test_page_code_blocks_run(page, scratch):
    if page not in RUN_BOUND:
        run_page(page, scratch)
        return
    env = default_optimization_env()
    # this process's imports (the jaxvisco under test, installed or not), and the tests' helpers
    env["PYTHONPATH"] = os.pathsep.join([os.path.dirname(__file__)] + [p for p in sys.path if p])
    env["MPLBACKEND"] = "Agg"
    p = subprocess.run([sys.executable, __file__, page], cwd=scratch, env=env, capture_output=True, text=True,
                       timeout=840)
    assert p.returncode == 0, f"{page}:\n{p.stderr[-3000:]}"


def docstring_objects():
    from test_docs import api_entries, resolve

    out = []
    for ident, members in api_entries().items():
        obj = resolve(ident)
        out.append((ident, obj))
        out += [(f"{ident}.{m}", getattr(obj, m)) for m in members]
    return out


@pytest.mark.timeout(900)
def test_docstring_examples_run(scratch):
    """The `python` blocks of every docstring that the API pages render."""
    ran = 0
    for name, obj in docstring_objects():
        for i, (lang, body, skip, _) in enumerate(blocks(inspect.getdoc(obj) or "")):
            assert lang == "python" and skip is None, f"{name}: docstring block {i + 1} is ```{lang}"
            with contextlib.redirect_stdout(open(os.devnull, "w")):
                exec(compile(body, f"{name} docstring, block {i + 1}", "exec"), {"__name__": "__doc_example__"})
            ran += 1
    assert ran >= 25, ran


if __name__ == "__main__":  # one page's blocks, in the current directory (`RUN_BOUND`)
    import pathlib

    jax.config.update("jax_enable_x64", True)
    run_page(sys.argv[1], pathlib.Path.cwd())
