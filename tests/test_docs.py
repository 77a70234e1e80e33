"""The documentation site (issue #61): it builds with `mkdocs build --strict` (no broken
link or reference, every API page's names resolved), every public name is on an API
page with a docstring that is reference (no private modules, no measurement logs), and
the gallery shows exactly the pictures its example scripts draw."""

import importlib.util
import inspect
import os
import re
import subprocess
import sys
import time

import pytest

import jaxvisco as jv

ROOT = os.path.abspath(os.path.join(os.path.dirname(__file__), os.pardir))
DOCS = os.path.join(ROOT, "docs")
# Docstrings exempt from the reference checks (none since #59, #60 and #63 landed).
NOT_YET = set()


def api_entries():
    """{identifier: [members]} of every `::: identifier` on the API pages."""
    out = {}
    for name in sorted(os.listdir(os.path.join(DOCS, "api"))):
        text = open(os.path.join(DOCS, "api", name), encoding="utf-8").read()
        for block in re.split(r"\n(?=::: )", text):
            m = re.match(r"::: (\S+)", block)
            if m:
                out[m.group(1)] = re.findall(r"^ {8}- (\w+)$", block, flags=re.M)
    return out


def resolve(identifier):
    obj = importlib.import_module("jaxvisco")
    for part in identifier.split(".")[1:]:
        obj = getattr(obj, part)
    return obj


def public_names():
    names = [f"jaxvisco.{n}" for n in vars(jv) if not n.startswith("_") and not inspect.ismodule(getattr(jv, n))]
    names += [f"jaxvisco.scenes.{n}" for n in ("lshape", "specimen", "Specimen")]
    names += [f"jaxvisco.time_functions.{n}" for n in vars(jv.time_functions) if not n.startswith("_") and
              n != "TIME_FUNCTIONS" and not inspect.ismodule(getattr(jv.time_functions, n))]
    return sorted(set(names) - {"jaxvisco.__version__"})


def test_every_public_name_is_on_an_api_page_with_a_docstring():
    entries = api_entries()
    missing = [n for n in public_names() if n not in entries]
    assert not missing, f"public names on no API page (docs/api/*.md): {missing}"
    unknown = [n for n in entries if n not in public_names()]
    assert not unknown, f"API pages name what jaxvisco does not export: {unknown}"
    for ident, members in entries.items():
        obj = resolve(ident)
        assert (inspect.getdoc(obj) or "").strip(), f"{ident} has no docstring"
        for m in members:
            assert (inspect.getdoc(getattr(obj, m)) or "").strip(), f"{ident}.{m} has no docstring"


PRIVATE = re.compile(r"`[^`]*\b_[a-z][\w.]*`|jaxvisco/_|\b_[a-z][a-z_]+\.[a-zA-Z_]+\b|THEORY §|session \d+")


def test_public_docstrings_are_reference():
    """No private modules or measurement logs in what the API pages render; the
    `**Arguments:**`-style headings stand on their own line with a blank one after
    (Markdown lists need it); long docstrings stay short of a measurement log."""
    for ident, members in api_entries().items():
        if ident.split(".")[-1] in NOT_YET:
            continue
        obj = resolve(ident)
        for name, o in [(ident, obj)] + [(f"{ident}.{m}", getattr(obj, m)) for m in members]:
            doc = inspect.getdoc(o) or ""
            assert not PRIVATE.findall(doc), f"{name}: private module or session log {PRIVATE.findall(doc)}"
            bad = re.findall(r"\*\*(?:Arguments|Returns|Raises|Attributes|Example):\*\*[^\n]|"
                             r"\*\*(?:Arguments|Returns|Raises|Attributes|Example):\*\*\n[^\n]", doc)
            assert not bad, f"{name}: put a blank line after {bad[0][:14]!r}"
            prose = re.sub(r"```.*?```", "", doc, flags=re.S).split()
            assert len(prose) < 450, f"{name}: {len(prose)} words of prose; move measurements to the docs"


def test_gallery_shows_the_pictures_its_scripts_draw():
    spec = importlib.util.spec_from_file_location("make_gallery", os.path.join(DOCS, "make_gallery.py"))
    gallery = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(gallery)
    page = open(os.path.join(DOCS, "gallery.md"), encoding="utf-8").read()
    shown = sorted(re.findall(r"!\[[^\]]*\]\(gallery/(\w+)\.png\)", page))
    assert shown == sorted(gallery.GALLERY), (shown, sorted(gallery.GALLERY))
    for name in shown:
        png = os.path.join(DOCS, "gallery", name + ".png")
        assert os.path.getsize(png) > 10_000, png
        assert f'--8<-- "examples/{name}.py"' in page  # the script beside its picture
    assert sorted(f[:-4] for f in os.listdir(os.path.join(DOCS, "gallery"))) == shown


def test_readme_is_short_and_starts_with_the_two_commands():
    text = open(os.path.join(ROOT, "README.md"), encoding="utf-8").read()
    assert len(text.splitlines()) <= 150
    fence = re.search(r"```\n(.*?)```", text, flags=re.S).group(1)
    assert fence.splitlines() == ['pip install . && jaxvisco paper --quick --out paper-out',
                                  'pip install ".[dev]" && pytest']
    assert text.index("```") < text.index("\n## ")  # the first thing after the title line


@pytest.mark.timeout(300)
def test_docs_build_strict(tmp_path):
    """`mkdocs build --strict`: the whole site, the API pages generated from the
    docstrings and the benchmarks pages from `benchmarks/results/*.json`."""
    env = dict(os.environ, DISABLE_MKDOCS_2_WARNING="true", NO_MKDOCS_2_WARNING="1",
               PYTHONPATH=os.pathsep.join([ROOT] + [p for p in sys.path if p]))
    start = time.perf_counter()
    p = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "-q", "-d", str(tmp_path / "site")],
                       cwd=ROOT, env=env, capture_output=True, text=True, timeout=280)
    wall = time.perf_counter() - start
    assert p.returncode == 0, p.stderr[-4000:]
    pages = [os.path.join(d, f) for d, _, fs in os.walk(tmp_path / "site") for f in fs if f == "index.html"]
    print(f"docs: {len(pages)} pages in {wall:.1f} s")
    html = open(tmp_path / "site" / "api" / "simulating" / "index.html", encoding="utf-8").read()
    assert "root_finder" in html and "<li><code>scene</code>" in html  # the docstring's list rendered
    bench = open(tmp_path / "site" / "benchmarks" / "index.html", encoding="utf-8").read()
    assert "summary.json" in bench and "Targets of issue #16" in bench
    assert len(pages) >= 40
