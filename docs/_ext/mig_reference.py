"""Reference pages generated from the code, so that they cannot drift from it.

A page holds a marker line, ``<!-- mig:NAME -->``, which this extension replaces (Sphinx's ``source-read`` event)
with Markdown made from the code at build time:

- ``commands``: every ``mi-gs`` command and option, from the argparse parsers (``mi_gaussians.cli.build_parser``),
  as Sphinx ``program`` / ``option`` descriptions (indexed and searchable); the options of ``mi-gs optimize`` name the
  training settings they give (``mi_gaussians.cli.train_options``).
- ``settings``: every training setting as ``--set`` names it (``densify.grad_threshold``), with its type, default,
  range and the comment that explains it in ``mi_gaussians/config.py`` (``mig_settings``), as ``setting`` objects
  (indexed, searchable, and linked with ``{setting}`densify.grad_threshold```).
- ``integrator``: the ``gaussian_splatting`` integrator's parameters, from its docstring (Mitsuba's plugin-reference
  format: ``pluginparameters``, ``tabs`` / ``code-tab``), checked against the names ``plugins/contract.py`` declares.
- ``run-folder``: the files of a run folder, from the names in ``mi_gaussians/run_folder.py``; a name without a
  description here fails the build.

Anything that does not match (an undocumented integrator parameter, an output file without a description, an unknown
marker) is a Sphinx warning, which ``-W`` turns into a failed build.
"""

from __future__ import annotations

import argparse
import ast
import copy
import re
import textwrap
from pathlib import Path

from docutils import nodes
from docutils.parsers.rst import Directive, directives
from docutils.parsers.rst.directives.tables import ListTable
from sphinx.util import logging

import mig_settings

logger = logging.getLogger(__name__)

MARKER = re.compile(r"^<!-- mig:([a-z-]+) -->$", re.M)
_MD_SPECIAL = re.compile(r"([\\`*_\[\]<>{}|#~$!])")


def md_escape(text: str) -> str:
    """Plain text as Markdown that shows it as it is (CommonMark's backslash escapes)."""
    return _MD_SPECIAL.sub(r"\\\1", text)


def code(text: str) -> str:
    """Inline code that may hold backticks."""
    fence = "``" if "`" in text else "`"
    pad = " " if text.startswith("`") or text.endswith("`") else ""
    return f"{fence}{pad}{text}{pad}{fence}"


# ---------------------------------------------------------------------------------------------------- commands
def _subcommands(parser: argparse.ArgumentParser):
    action = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    helps = {a.dest: a.help for a in action._choices_actions}
    return [(name, sub, helps.get(name, "")) for name, sub in action.choices.items()]


def _signature(action: argparse.Action, formatter: argparse.HelpFormatter) -> str:
    if not action.option_strings:
        return action.metavar or action.dest
    if action.nargs == 0:
        return ", ".join(action.option_strings)
    shown = copy.copy(action)
    if shown.choices is not None and shown.metavar is None:
        shown.metavar = action.dest.upper()
    args = formatter._format_args(shown, action.dest.upper())
    return ", ".join(f"{flag} {args}" for flag in action.option_strings)


def _option_text(action: argparse.Action, formatter: argparse.HelpFormatter, settings_of: dict) -> str:
    parts = [md_escape(_sentence(formatter._expand_help(action))) if action.help else ""]
    if action.choices is not None:
        parts.append("Choices: " + ", ".join(code(str(c)) for c in action.choices) + ".")
    if isinstance(action, argparse._AppendAction):
        parts.append("Repeatable.")
    if isinstance(action, argparse.BooleanOptionalAction):
        parts.append(f"Default: {code(str(action.default))}." if action.default is not None else "")
    keys = settings_of.get(action.dest)
    if keys:
        parts.append("Gives " + " / ".join(f"{{setting}}`{k}`" for k in keys) + ".")
    return " ".join(p for p in parts if p)


def commands_markdown() -> str:
    from mi_gaussians.cli import COMMANDS, build_parser
    from mi_gaussians.cli.train_options import options

    parser = build_parser()
    formatter = argparse.HelpFormatter("mi-gs", width=100)
    settings_of = {opt.dest: opt.keys for opt in options()}
    out = ["| command | what it does |", "| --- | --- |"]
    subs = _subcommands(parser)
    names = [name for name, _, _ in subs]
    if tuple(names) != tuple(COMMANDS):
        logger.warning(f"mig_reference: the parser's commands {names} are not cli.COMMANDS {list(COMMANDS)}")
    for name, _, help_ in subs:
        out.append(f"| {{ref}}`mi-gs {name} <command-{name}>` | {md_escape(help_ or '')} |")
    out.append("")
    for name, sub, help_ in subs:
        out += [f"(command-{name})=", f"## `mi-gs {name}`", "", md_escape(_sentence(help_ or "")), "",
                "```text", sub.format_usage().strip(), "```", "", f"```{{program}} mi-gs {name}", "```", ""]
        for group in sub._action_groups:
            actions = [a for a in group._group_actions if not isinstance(a, argparse._HelpAction)]
            if not actions:
                continue
            out += [f"### {group.title[0].upper() + group.title[1:]}", ""]
            if group.description:
                out += [md_escape(group.description), ""]
            for action in actions:
                out += [f"```{{option}} {_signature(action, formatter)}",
                        _option_text(action, formatter, settings_of if name == "optimize" else {}), "```", ""]
    return "\n".join(out)


# ---------------------------------------------------------------------------------------------------- settings
def _range_text(key: str) -> str:
    from mi_gaussians.config import RULES, Range

    rule = RULES.get(key)
    if isinstance(rule, tuple):
        return "one of " + ", ".join(code(r) for r in rule)
    if isinstance(rule, Range):
        text = str(rule)
        if rule.counts:
            lo, hi = rule.counts
            text += f" (each of {lo} values)" if lo == hi else f" (each of {lo} to {hi} values)"
        return md_escape(text)
    return ""


def settings_markdown() -> str:
    from mi_gaussians.cli.train_options import options

    flags_of: dict[str, list[str]] = {}
    for opt in options():
        for key in opt.keys:
            flags_of.setdefault(key, []).append("/".join(opt.flags))
    docs = mig_settings.section_docs()
    items = mig_settings.settings()
    out = ["| setting | default |", "| --- | --- |"]
    for s in items:
        out.append(f"| {{setting}}`{s.key}` | {code(mig_settings.set_text(s.default))} |")
    out.append("")
    section = None
    for s in items:
        if s.section != section:
            section = s.section
            cls, doc = docs[section]
            title = f"`{section}`: {cls}" if section else f"Top level: {cls}"
            out += [f"(settings-{section or 'top'})=", f"## {title}", ""]
            if doc:
                out += [md_escape(doc), ""]
            if section:
                out += [f"Set with `--set {section}.FIELD=VALUE`.", ""]
            else:
                out += ["Set with `--set FIELD=VALUE`.", ""]
        lines = [f"Default {code(s.key + '=' + mig_settings.set_text(s.default))}"
                 + (f" ({code(s.source)} in `config.py`)" if s.source and _differs(s) else "")
                 + f"; type {code(s.type)}"
                 + (f"; {_range_text(s.key)}" if _range_text(s.key) else "") + "."]
        if s.group:
            others = [k for k in s.group if k != s.key]
            lines.append(md_escape(_sentence(s.joined)) + " (One comment for " + ", ".join(
                f"{{setting}}`{k}`" for k in others) + " and this setting.)")
        elif s.comment:
            lines.append(md_escape(_sentence(s.comment)))
        if s.key in flags_of:
            lines.append("Given by " + ", ".join(code(f) for f in flags_of[s.key]) + " of "
                         "{ref}`mi-gs optimize <command-optimize>`.")
        out += [f"```{{setting}} {s.key}", "\n\n".join(lines), "```", ""]
    return "\n".join(out)


def _differs(s: mig_settings.Setting) -> bool:
    shown = mig_settings.set_text(s.default)
    plain = s.source.replace("_", "").strip("\"'")
    return plain not in (shown, str(s.default), repr(s.default)) and s.source not in ("None", "()")


def _sentence(text: str) -> str:
    text = text.strip()
    if not text:
        return text
    return text if text.endswith((".", ")", "!", "?")) else text + "."


# ---------------------------------------------------------------------------------------------------- integrator
_SUBSTITUTIONS = {name: name for name in ("float", "int", "bool", "string", "rgb", "spectrum", "tensor", "texture")}


def _class_docstring(path: Path, cls_name: str) -> str:
    tree = ast.parse(path.read_text())
    for node in ast.walk(tree):
        if isinstance(node, ast.ClassDef) and node.name == cls_name:
            return ast.get_docstring(node, clean=True) or ""
    raise LookupError(f"{path}: no class {cls_name}")


def integrator_markdown() -> str:
    import importlib.util

    from mi_gaussians.plugins import contract

    spec = importlib.util.find_spec("mi_gaussians.plugins")
    path = Path(list(spec.submodule_search_locations)[0]) / "splat_integrator.py"
    doc = _class_docstring(path, "GaussianSplattingIntegrator")
    lines = doc.splitlines()
    # the docstring opens with its label and title (Mitsuba's format); the page gives them as Markdown
    while lines and (not lines[0].strip() or lines[0].startswith(".. _")):
        lines.pop(0)
    title = lines.pop(0)
    if lines and set(lines[0].strip()) == {"-"}:
        lines.pop(0)
    body = "\n".join(lines)
    declared = {getattr(contract, n) for n in dir(contract)
                if n.isupper() and isinstance(getattr(contract, n), str) and n != "INTEGRATOR"}
    documented = set(re.findall(r"^\s*\* - (\w+)\s*$", body, re.M))
    for name in sorted(declared - documented):
        logger.warning(f"mig_reference: the integrator parameter {name!r} (plugins/contract.py) is not documented "
                       f"in GaussianSplattingIntegrator's docstring")
    for name in sorted(documented - declared):
        logger.warning(f"mig_reference: the integrator's docstring documents {name!r}, which plugins/contract.py "
                       f"does not declare")
    if f":monosp:`{contract.INTEGRATOR}`" not in title:
        logger.warning(f"mig_reference: the integrator's docstring title does not name {contract.INTEGRATOR!r}")
    heading = re.sub(r":monosp:`([^`]*)`", r"`\1`", title)
    # Mitsuba's type substitutions (|float|, |rgb|, ...) as the emphasised type names its reference shows
    body = re.sub(r"\|(" + "|".join(_SUBSTITUTIONS) + r")\|", lambda m: f"*{_SUBSTITUTIONS[m.group(1)]}*", body)
    return "\n".join([f"(integrator-{contract.INTEGRATOR})=", f"## {heading}", "", "```{eval-rst}", body, "```", ""])


class PluginParameters(ListTable):
    """Mitsuba's ``pluginparameters``: a list table of parameter, type and description, with a header row."""

    option_spec = {**ListTable.option_spec}

    def run(self):
        from docutils.statemachine import StringList

        header = StringList(["* - Parameter", "  - Type", "  - Description", ""], source="pluginparameters")
        self.content = header + self.content
        self.options.setdefault("header-rows", 1)
        self.options.setdefault("widths", [18, 14, 68])
        self.options.setdefault("class", ["pluginparameters"])
        return super().run()


class Tabs(Directive):
    """``tabs`` (as sphinx-tabs writes them in Mitsuba's docstrings): here each tab is shown after the other."""

    has_content = True

    def run(self):
        node = nodes.container(classes=["mig-tabs"])
        self.state.nested_parse(self.content, self.content_offset, node)
        return [node]


class CodeTab(Directive):
    """``code-tab LANGUAGE``: one tab of code, shown as a literal block captioned with its language."""

    has_content = True
    required_arguments = 1
    final_argument_whitespace = True

    def run(self):
        language = self.arguments[0].strip()
        text = "\n".join(self.content)
        block = nodes.literal_block(text, text, language=language)
        caption = {"xml": "XML", "python": "Python"}.get(language, language)
        container = nodes.container(classes=["literal-block-wrapper"], literal_block=True)
        container += nodes.caption(caption, caption)
        container += block
        return [container]


def monosp_role(name, rawtext, text, lineno, inliner, options=None, content=None):
    return [nodes.literal(rawtext, text)], []


# ---------------------------------------------------------------------------------------------------- run folder
#: What each name of ``mi_gaussians/run_folder.py`` is, for the reader of a run folder. A name the module defines
#: and this table lacks fails the build; so does an entry for a name the module no longer defines.
RUN_FOLDER = {
    "MODEL": "The model: the Gaussians in the 3DGS PLY layout (loads in Mitsuba's `ellipsoids` shape and in 3DGS "
             "viewers).",
    "_SAVED_MODELS": "The models saved at the iterations of `save_iterations` (7,000 and 30,000 by default), when the "
                     "run passes them.",
    "CONFIG": "The run's record: its resolved training settings (`train`, every setting of "
              "[the settings reference](settings.md)), the dataset and its fingerprint, and for a Mitsuba scene the "
              "references folder. `--resume` continues with it; it is read with every value's type and range "
              "checked.",
    "CHECKPOINTS": "The folder of the checkpoint.",
    "CHECKPOINT": "The checkpoint `--resume` continues from: the model, Adam's moments, the densification state, "
                  "the random-number states and the history (every `checkpoint_every` iterations and at the end).",
    "METRICS": "The held-out scores: PSNR and SSIM per view and their means (LPIPS-VGG only when torch, `lpips` and "
               "the VGG weights are already on the machine: nothing is downloaded), the number of Gaussians, the "
               "scene extent (`extent`), training time, iterations per second, `loop` (where the training time went) "
               "and, for a Mitsuba scene, `depth_mae` and `depth_coverage`; with `--pose-opt` and known pose errors, "
               "`poses`.",
    "EVAL": "What `mi-gs eval` recomputes on the test views (the same record as `metrics.json`'s scores).",
    "HISTORY": "Loss, held-out PSNR and number of Gaussians against the iteration.",
    "CURVES": "The same as a plot.",
    "RENDERS": "The held-out views rendered by the model: linear EXR and sRGB PNG per view.",
    "COMPARE": "Reference, render and error side by side, per held-out view.",
    "GAUSSIAN_SCENE": "A Mitsuba scene that renders the model with the `gaussian_splatting` integrator from the "
                      "first held-out camera (with the run's background, colour space and anti-aliasing).",
    "CAMERAS": "The run's cameras, `{\"train\": [...], \"test\": [...]}`, each a [camera JSON](camera-json.md); "
               "the training cameras as the run trained from them.",
    "REFINED_CAMERAS": "With `--pose-opt`: the training cameras as the run refined them (camera JSON).",
    "REFINED_IMAGES": "With `--pose-opt`: the same poses in COLMAP's `images.txt` layout (camera ids number the "
                      "distinct intrinsics in order, at the run's resolution).",
    "EXPOSURE": "With `--exposure`: each training image's 3x4 colour transform (never folded into the model).",
    "EXPOSURE_GRIDS": "With `--exposure bilateral`: each training image's bilateral grid.",
    "REFERENCES": "A Mitsuba scene's path-traced references, `references/<key>/` (linear EXR, exact depth "
                  "`<view>.depth.npy`, and `rig.json`, the cameras), reused by later runs and kept by "
                  "`--overwrite` (`--cache DIR` puts them elsewhere).",
    "POINTS": "Triangulated initial points, cached in `points/<key>/` (kept by `--overwrite`; `--cache DIR` puts "
              "them elsewhere).",
    "LOCK": "The lock that makes the folder one run's (holds the PID of the process using it; released by the "
            "operating system however the process ends).",
    "Manifest.FILE": "Every file and folder a run of this folder claimed before writing it: `--overwrite` removes "
                     "exactly these, and nothing else.",
}


def run_folder_markdown() -> str:
    from mi_gaussians import run_folder

    source = Path(run_folder.__file__).read_text()
    comments = {}
    for node in ast.parse(source).body:
        if isinstance(node, ast.Assign) and len(node.targets) == 1 and isinstance(node.targets[0], ast.Name):
            comments[node.targets[0].id] = node.lineno
    names = {n: getattr(run_folder, n) for n in vars(run_folder)
             if n.lstrip("_").isupper() and isinstance(getattr(run_folder, n), str)}
    names["Manifest.FILE"] = run_folder.Manifest.FILE
    for n in sorted(set(names) - set(RUN_FOLDER)):
        logger.warning(f"mig_reference: run_folder.{n} = {names[n]!r} has no description in docs/_ext/"
                       f"mig_reference.py (RUN_FOLDER)")
    for n in sorted(set(RUN_FOLDER) - set(names)):
        logger.warning(f"mig_reference: RUN_FOLDER describes run_folder.{n}, which the module no longer defines")
    out = ["| path in the run folder | name in `run_folder.py` | what it holds |", "| --- | --- | --- |"]
    order = [n for n in RUN_FOLDER if n in names]
    for n in order:
        path = names[n] + ("/" if n in ("CHECKPOINTS", "RENDERS", "COMPARE", "REFERENCES", "POINTS") else "")
        out.append(f"| {code(path)} | {code(n)} | {RUN_FOLDER[n]} |")
    outputs = ", ".join(code(x) for x in run_folder.RUN_OUTPUTS)
    out += ["", f"The names a run writes at the top of its folder (`RUN_OUTPUTS`): {outputs}.", ""]
    return "\n".join(out)


# ---------------------------------------------------------------------------------------------------- wiring
GENERATORS = {"commands": commands_markdown, "settings": settings_markdown, "integrator": integrator_markdown,
              "run-folder": run_folder_markdown}


def _source_read(app, docname, source):
    text = source[0]
    found = MARKER.findall(text)
    if not found:
        return
    app.env.mig_generated = getattr(app.env, "mig_generated", set()) | {docname}

    def generate(match):
        name = match.group(1)
        if name not in GENERATORS:
            logger.warning(f"mig_reference: unknown marker <!-- mig:{name} --> in {docname}")
            return ""
        return GENERATORS[name]()

    source[0] = MARKER.sub(generate, text)


def _outdated(app, env, added, changed, removed):
    # the generated pages depend on the code, not only on their source: read them again at every build
    return sorted(getattr(env, "mig_generated", set()) - set(removed))


def _no_generated_dataclass_docstring(app, what, name, obj, options, lines):
    # a dataclass without a docstring gets "Name(field: type, ...)" from @dataclass: the fields are shown anyway
    if what == "class" and lines and re.match(rf"^{re.escape(name.rsplit('.', 1)[-1])}\(", lines[0]):
        lines.clear()


def setup(app):
    app.add_object_type("setting", "setting", objname="training setting",
                        indextemplate="pair: %s; training setting")
    app.add_directive("pluginparameters", PluginParameters)
    app.add_directive("tabs", Tabs)
    app.add_directive("code-tab", CodeTab)
    app.add_role("monosp", monosp_role)
    app.connect("source-read", _source_read)
    app.connect("env-get-outdated", _outdated)
    app.connect("autodoc-process-docstring", _no_generated_dataclass_docstring)
    return {"version": "1", "parallel_read_safe": True, "parallel_write_safe": True, "env_version": 1}
