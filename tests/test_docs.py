"""The documentation (``docs/``, Sphinx with MyST Markdown and the furo theme).

It builds with warnings as errors (once per session, into a temporary folder); its reference pages, generated from
the code, hold every ``mi-gs`` command and long option, every training setting as ``--set`` names it (with a
default that ``--set`` reads back as the default), every parameter of the integrator and every file of a run folder;
every ``mi-gs`` command that the pages and the README show parses with the real parser, and every benchmark script
they name exists; the integrator tutorial's script runs and does what the page says; the README stays a front page
with its two set-up commands; and in Debian's headless Chromium the built site works offline from ``file://``: the
front page, the command reference and a search for a setting, with a screenshot of the front page."""

from __future__ import annotations

import argparse
import html
import importlib.util
import re
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
SETTING = "densify.grad_threshold"


@pytest.fixture(scope="module")
def site(tmp_path_factory) -> Path:
    """The site built as the README says (warnings as errors), into a temporary folder."""
    if importlib.util.find_spec("sphinx") is None or importlib.util.find_spec("myst_parser") is None:
        pytest.fail("the documentation's packages are not installed: pip install '.[test]' (or '.[docs]')")
    out = tmp_path_factory.mktemp("docs") / "html"
    res = subprocess.run([sys.executable, "-m", "sphinx", "-W", "--keep-going", "-q", "-b", "html", str(DOCS),
                          str(out)], capture_output=True, text=True, timeout=900, cwd=ROOT)
    assert res.returncode == 0, f"sphinx-build failed:\n{res.stdout[-2000:]}\n{res.stderr[-4000:]}"
    return out


def _text(page: Path) -> str:
    """A built page's text, tags stripped and entities decoded."""
    return html.unescape(re.sub(r"<[^>]+>", "", page.read_text()))


def _ids(page: Path) -> set[str]:
    return set(re.findall(r'\bid="([^"]+)"', page.read_text()))


def _generators():
    sys.path.insert(0, str(DOCS / "_ext"))
    try:
        import mig_settings
    finally:
        sys.path.remove(str(DOCS / "_ext"))
    return mig_settings


def _subparsers():
    from mi_gaussians.cli import build_parser

    parser = build_parser()
    action = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return parser, action.choices


def test_the_site_builds_with_warnings_as_errors(site):
    for page in ("index", "getting-started", "reference/cli", "reference/settings", "reference/integrator",
                 "reference/python-api", "reference/run-folder", "reference/camera-json", "benchmarks/index",
                 "search"):
        assert (site / f"{page}.html").is_file(), page
    assert (site / "searchindex.js").is_file()
    # nothing of the site is fetched from elsewhere: no remote scripts, styles or images in any page
    for page in site.rglob("*.html"):
        remote = re.findall(r'<(?:script|link|img)[^>]+(?:src|href)="(https?://[^"]+)"', page.read_text())
        assert not remote, (page, remote)


def test_every_command_and_long_option_is_in_the_reference(site):
    page = site / "reference" / "cli.html"
    text, ids = _text(page), _ids(page)
    _, commands = _subparsers()
    missing = []
    for name, sub in commands.items():
        if f"mi-gs {name}" not in text:
            missing.append(f"mi-gs {name}")
        for action in sub._actions:
            for flag in action.option_strings:
                if not flag.startswith("--") or flag == "--help":
                    continue
                if flag not in text or f"cmdoption-mi-gs-{name}-{flag[2:].lower()}" not in ids:
                    missing.append(f"mi-gs {name} {flag}")
    assert not missing, f"not in the built command reference: {missing}"


def test_every_training_setting_is_in_the_reference_with_a_default_that_set_reads_back(site):
    from mi_gaussians.config import TrainConfig, setting_items

    page = site / "reference" / "settings.html"
    text, ids = _text(page), _ids(page)
    gen = _generators()
    shown = {s.key: gen.set_text(s.default) for s in gen.settings()}
    keys = [key for key, _ in setting_items(TrainConfig())]
    assert sorted(shown) == sorted(keys) and SETTING in keys
    for key in keys:
        assert f"setting-{key}" in ids, f"{key}: no entry in the settings reference"
        assert f"{key}={shown[key]}" in text, f"{key}: its default is not shown as {key}={shown[key]}"
        # the default, spelt as the page shows it, is what --set reads as the default
        assert TrainConfig().with_settings([f"{key}={shown[key]}"]) == TrainConfig(), key


def test_the_integrator_and_run_folder_references_are_complete(site):
    from mi_gaussians import run_folder
    from mi_gaussians.plugins import contract

    text = _text(site / "reference" / "integrator.html")
    for name in (contract.BACKGROUND, contract.SH_DEGREE, contract.DEPTH_AOV, contract.COLOR_SPACE,
                 contract.ANTIALIASED, contract.INTEGRATOR):
        assert name in text, name
    text = _text(site / "reference" / "run-folder.html")
    for name in run_folder.RUN_OUTPUTS + (run_folder.CHECKPOINT, run_folder.LOCK, run_folder.Manifest.FILE):
        assert name in text, name


def _bash_lines(path: Path):
    """(line number, text) of every command line of the ```bash blocks of a Markdown file, a line ending in a
    backslash joined with the next as the shell joins them."""
    inside, start, held = False, 0, ""
    for i, line in enumerate(path.read_text().splitlines(), 1):
        if line.strip().startswith("```"):
            inside = line.strip() == "```bash" if not inside else False
            continue
        if inside:
            start = start or i
            if line.endswith("\\"):
                held += line[:-1]
                continue
            yield start, held + line
            start, held = 0, ""


def test_every_mi_gs_command_the_pages_show_parses():
    """Each ``mi-gs ...`` of a bash block in the docs and the README, as the real parser reads it."""
    parser, _ = _subparsers()
    checked, bad = 0, []
    for path in [ROOT / "README.md", *sorted(DOCS.rglob("*.md"))]:
        if "_build" in path.parts:
            continue
        for i, line in _bash_lines(path):
            lexer = shlex.shlex(line, posix=True, punctuation_chars=True)
            lexer.whitespace_split = True
            commands, words = [], []
            for token in lexer:
                if token in ("&&", "||", ";", "|", "&"):
                    commands.append(words)
                    words = []
                else:
                    words.append(token)
            for words in commands + [words]:
                if not words or words[0] != "mi-gs":
                    continue
                checked += 1
                try:
                    parser.parse_args(words[1:])
                except SystemExit:
                    bad.append(f"{path.relative_to(ROOT)}:{i}: {' '.join(words)}")
    assert checked >= 30 and not bad, f"commands the pages show that mi-gs refuses: {bad}"


def test_every_benchmark_script_the_pages_name_exists():
    named = set()
    for path in [ROOT / "README.md", *DOCS.rglob("*.md")]:
        if "_build" not in path.parts:
            named |= set(re.findall(r"benchmarks/\w+\.(?:py|sh)", path.read_text()))
    assert named and not [n for n in sorted(named) if not (ROOT / n).is_file()]


def test_the_integrator_tutorial_runs(tmp_path):
    """The script of "The integrator inside Mitsuba" fits the colours back: the loss falls 100-fold."""
    page = (DOCS / "tutorials" / "integrator.md").read_text()
    script = page.split("## In Python, differentiating through it", 1)[1].split("```python\n", 1)[1].split("```", 1)[0]
    (tmp_path / "scenes").symlink_to(ROOT / "scenes")
    (tmp_path / "fit.py").write_text(script)
    res = subprocess.run([sys.executable, "fit.py"], cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr[-2000:]
    losses = [float(x) for x in re.findall(r"loss ([0-9.]+)", res.stdout)]
    assert len(losses) >= 2 and losses[-1] < losses[0] / 100, res.stdout
    assert (tmp_path / "fitted.png").stat().st_size > 0


def test_the_readme_is_a_front_page_with_its_two_set_up_commands():
    readme = (ROOT / "README.md").read_text()
    assert len(readme.splitlines()) <= 200
    for marker in ("<!-- ci:main -->", "<!-- ci:test -->"):
        assert readme.count(marker) == 1
        after = readme.split(marker, 1)[1].lstrip("\n").splitlines()
        assert after[0] == "```bash" and after[1].startswith(("python3 -m venv", ". .venv/bin/activate"))
    # (the docs' own build command lives in the docs, not among the front page's set-up commands)
    assert readme.count("```bash") >= 2 and "sphinx-build" not in readme
    testing = (ROOT / "docs" / "explanation" / "testing.md").read_text()
    assert "sphinx-build -W --keep-going -b html docs docs/_build/html" in testing


def _nonblank(path: Path) -> np.ndarray:
    from PIL import Image

    img = np.asarray(Image.open(path).convert("RGB"), np.float64) / 255.0
    assert img.shape[0] >= 400 and img.shape[1] >= 600
    assert img.std() > 0.05 and (img < 0.5).mean() > 0.005, f"{path}: the screenshot is blank"
    return img


def test_the_site_works_offline_in_chromium(site, tmp_path):
    """Front page (with its picture), command reference and a search for a setting, from file:// with every
    request outside the site refused; a screenshot of the front page."""
    if CHROMIUM is None:
        pytest.skip("no Chromium on this machine (Debian: apt-get install chromium) for the browser tests")
    try:
        from playwright.sync_api import sync_playwright
    except ImportError:
        pytest.skip("Playwright is not installed (pip install '.[test]')")
    outside: list[str] = []

    def only_files(route):
        if route.request.url.startswith("file://"):
            route.continue_()
        else:
            outside.append(route.request.url)
            route.abort()

    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=CHROMIUM, args=["--no-sandbox"])
        try:
            page = browser.new_page(viewport={"width": 1280, "height": 900})
            page.route("**/*", only_files)
            page.goto((site / "index.html").as_uri())
            assert "mi-gaussians" in page.title()
            assert page.evaluate("Array.from(document.images).every(i => i.complete && i.naturalWidth > 0)")
            assert page.locator("text=Getting started").first.is_visible()
            page.screenshot(path=str(tmp_path / "site.png"))
            _nonblank(tmp_path / "site.png")

            page.goto((site / "reference" / "cli.html").as_uri())
            assert page.locator("#command-optimize").count() == 1
            assert page.locator("#cmdoption-mi-gs-optimize-iterations").is_visible()
            page.goto((site / "reference" / "cli.html").as_uri() + "#cmdoption-mi-gs-optimize-resume")
            assert "--resume" in page.locator("#cmdoption-mi-gs-optimize-resume").inner_text()

            page.goto((site / "search.html").as_uri() + f"?q={SETTING}")
            result = page.locator(f'#search-results a[href*="settings.html#setting-{SETTING}"]')
            result.first.wait_for(timeout=30_000)
            result.first.click()
            page.wait_for_load_state()
            assert page.url.endswith(f"settings.html#setting-{SETTING}")
            assert page.locator(f'[id="setting-{SETTING}"]').is_visible()
        finally:
            browser.close()
    assert not outside, f"the site asked for something outside itself: {outside}"
    # the committed screenshot of the site (docs/site.png) is a picture too
    _nonblank(DOCS / "site.png")
