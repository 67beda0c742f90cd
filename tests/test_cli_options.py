"""The command line's training options as one table (``mi_gaussians.cli.train_options``), the strategy registry,
the typed reader of ``config.json`` (``run_folder.RunRecord``) and the rules of ``config.py``; and that no test or
benchmark reaches into a private name of the package."""

from __future__ import annotations

import ast
import dataclasses
import json
import typing
from pathlib import Path

import pytest

from mi_gaussians import config, run_folder
from mi_gaussians.cli import build_parser, train_options
from mi_gaussians.cli.errors import InputError
from mi_gaussians.config import STRATEGIES, TrainConfig

ROOT = Path(__file__).resolve().parents[1]

#: A value for each option of the table, unlike its default (a new option must be given one here).
EXAMPLES = {
    "--iterations": ["500"], "--resolution": ["2"], "--white-background": [], "--background": ["0.5"],
    "--random-background": [], "--absgrad": [], "--depth-weight": ["2"], "--strategy": ["mcmc"],
    "--max-gaussians": ["5000"], "--antialiased": [], "--sh-degree": ["1"], "--test-every": ["4"],
    "--random-points": ["1000"], "--seed": ["3"], "--checkpoint-every": ["50"], "--eval-every": ["0"],
    "--rig": ["sphere"], "--views": ["12"], "--test-views": ["2"], "--radius": ["4"], "--fov": ["30"],
    "--up": ["0", "0", "1"], "--spp": ["8"], "--linear": [], "--init": ["cube"], "--init-points": ["2000"],
    "--define": ["spp=4"], "--exposure": [], "--pose-opt": [],
}
SCENE_ONLY = {"--depth-weight"}          # (checked against the input: needs a scene file)


def parse(*argv):
    return build_parser().parse_args(["optimize", "input", "-o", "out", *argv])


def test_every_option_has_an_example():
    assert {opt.name for opt in train_options.options()} == set(EXAMPLES)


@pytest.mark.parametrize("flag", sorted(EXAMPLES))
def test_each_option_gives_its_settings_for_a_new_run_and_is_checked_on_resume(flag):
    """The table's keys are the settings the option changes (nothing else changes, except what --iterations
    scales), and the same entry refuses the option given again with another value on --resume."""
    opt = next(o for o in train_options.options() if o.name == flag)
    scene_file = flag in SCENE_ONLY or opt.scene
    extra = ["--strategy", "mcmc"] if flag == "--max-gaussians" else []
    cfg = train_options.new_run_config(parse(flag, *EXAMPLES[flag], *extra), scene_file)
    base = train_options.new_run_config(parse(*extra), scene_file)
    changed = {k for k, _ in config.setting_items(cfg)} and {
        k for (k, a), (_, b) in zip(config.setting_items(cfg), config.setting_items(base)) if a != b}
    scaled = {"optim.position_lr_max_steps", "densify.densify_until_iter", "mcmc.refine_stop_iter", "save_iterations"}
    assert changed and changed - scaled <= set(opt.keys), (changed, opt.keys)
    # --resume: the run's own value is accepted, another refused (or, for options that only change how the run
    # goes on, applied)
    same = train_options.resumed_config(parse(flag, *EXAMPLES[flag]), cfg, scene_file, "run/config.json")
    if opt.resume is not None:
        other = train_options.resumed_config(parse(flag, *EXAMPLES[flag]), base, scene_file, "run/config.json")
        assert all(train_options.setting(other, k) == train_options.setting(cfg, k) for k in opt.keys)
        return
    assert same == cfg
    with pytest.raises(InputError) as e:
        train_options.resumed_config(parse(flag, *EXAMPLES[flag]), base, scene_file, "run/config.json")
    assert f"{flag} gives {opt.keys[0]}" in str(e.value) and "run/config.json" in str(e.value)


def test_every_strategy_is_accepted_by_the_command_line_and_has_its_section():
    from mi_gaussians.optim.strategies import CLASSES, make_strategy

    assert set(CLASSES) == set(STRATEGIES) and len(STRATEGIES) >= 2
    for name, section in STRATEGIES.items():
        assert dataclasses.is_dataclass(getattr(TrainConfig(), section)), section
        cfg = train_options.new_run_config(parse("--strategy", name), scene_file=False)
        assert cfg.strategy == name
        assert isinstance(make_strategy(cfg, 1.0, white_background=False), CLASSES[name])
        # a setting of another strategy's section would be silently ignored: refused, naming it
        for other, other_section in STRATEGIES.items():
            if other == name:
                continue
            field = dataclasses.fields(getattr(TrainConfig(), other_section))[0].name
            key = f"{other_section}.{field}"
            value = getattr(getattr(TrainConfig(), other_section), field)
            with pytest.raises(InputError, match=f"configures --strategy {other}"):
                train_options.new_run_config(parse("--strategy", name, "--set", f"{key}={value}"), False)
    with pytest.raises(SystemExit):                                   # (argparse: not a choice)
        parse("--strategy", "sgd")


def test_shortened_runs_keep_the_papers_proportions():
    t = TrainConfig()
    short = t.with_iterations(3000)
    assert (short.optim.iterations, short.optim.position_lr_max_steps) == (3000, 3000)
    assert short.densify.densify_until_iter == 1500 and short.mcmc.refine_stop_iter == 2500
    assert short.save_iterations == () and t.with_iterations(9000).save_iterations == (7000,)
    long = t.with_iterations(40_000)                  # a longer run keeps the paper's densification window
    assert long.densify == t.densify and long.mcmc == t.mcmc and long.save_iterations == t.save_iterations
    assert t.optim.with_depth_weight(2.0).depth_weight_final == 2.0 / config.DEPTH_WEIGHT_DECAY


def test_rules_name_only_real_settings():
    keys = {k for k, _ in config.setting_items(TrainConfig())}
    assert set(config.RULES) <= keys, set(config.RULES) - keys
    assert TrainConfig().validate() == TrainConfig()


# ------------------------------------------------------------------------------------------- config.json record
def _wrong_value(kind):
    """A JSON value of the wrong type for a field annotated ``kind``."""
    args = typing.get_args(kind)
    if type(None) in args:
        kind = next(a for a in args if a is not type(None))
    if typing.get_origin(kind) is tuple:
        return "1,2,3"
    return {bool: "false", int: "300", float: "abc", str: 5}[kind]


def _fields():
    out = []
    for f in dataclasses.fields(TrainConfig):
        value = getattr(TrainConfig(), f.name)
        if dataclasses.is_dataclass(value):
            hints = typing.get_type_hints(type(value))
            out += [(f"{f.name}.{g.name}", hints[g.name]) for g in dataclasses.fields(value)]
        else:
            out.append((f.name, typing.get_type_hints(TrainConfig)[f.name]))
    return out


@pytest.mark.parametrize("key, kind", _fields(), ids=[k for k, _ in _fields()])
def test_each_field_of_config_json_with_a_wrong_type_is_one_line_naming_the_file_and_the_key(tmp_path, key, kind):
    record = TrainConfig().to_dict()
    section, _, name = key.rpartition(".")
    (record[section] if section else record)[name] = _wrong_value(kind)
    (tmp_path / "config.json").write_text(json.dumps({"dataset": "/data", "train": record}))
    with pytest.raises(ValueError) as e:
        run_folder.RunRecord.read(tmp_path, "missing")
    msg = str(e.value)
    assert "\n" not in msg and str(tmp_path / "config.json") in msg and f"'train.{key}'" in msg, msg


@pytest.mark.parametrize("change, words", [
    ({"train": {"checkpoint_every": 0}}, "'train.checkpoint_every': must be >= 1, got 0"),
    ({"train": {"optim": {"iterations": -3}}}, "'train.optim.iterations': must be >= 1"),
    ({"train": {"strategy": "sgd"}}, "'train.strategy': 'sgd' is not one of default, mcmc"),
    ({"train": {"optim": {"lambda_dssim": 1e400}}}, "'train.optim.lambda_dssim'"),      # (JSON Infinity)
    ({"train": {"optim": 5}}, "'train.optim': expected an object of settings"),
    ({"train": {"optim": {"nope": 1}}}, "'train.optim.nope': unknown setting"),
    ({"references": 7}, "key 'references': expected a string"),
    ({"later": 1}, "key 'later': not a key of an mi-gs run record"),
    ({"dataset": ""}, "does not name its dataset"),
])
def test_config_json_values_out_of_range_or_misplaced(tmp_path, change, words):
    record = {"dataset": "/data", "train": TrainConfig().to_dict()}
    for k, v in change.items():
        if isinstance(v, dict) and isinstance(record.get(k), dict):
            for k2, v2 in v.items():
                if isinstance(v2, dict) and isinstance(record[k].get(k2), dict):
                    record[k][k2].update(v2)
                else:
                    record[k][k2] = v2
        else:
            record[k] = v
    (tmp_path / "config.json").write_text(json.dumps(record))
    with pytest.raises(ValueError) as e:
        run_folder.RunRecord.read(tmp_path, "missing")
    assert words in str(e.value) and "\n" not in str(e.value), str(e.value)


def test_a_record_round_trips_and_older_records_still_load(tmp_path):
    cfg = TrainConfig().with_iterations(500).with_settings(["scene.resolution=64", "data.background=1,1,1"])
    record = run_folder.RunRecord("/data/scene.xml", cfg, references="/runs/a/references/abc")
    record.write(tmp_path)
    assert run_folder.RunRecord.read(tmp_path, "missing") == record
    saved = json.loads((tmp_path / "config.json").read_text())
    del saved["train"]["mcmc"]                            # (a record of a version without MCMC: defaults)
    saved["train"]["raster"]["tile_size"] = 16            # (a retired field: ignored)
    # (a record from before prune_large_after and max_screen_fraction: its large-Gaussian prunes began after the
    # first opacity reset; its pixel screen size is retired)
    del saved["train"]["densify"]["prune_large_after"], saved["train"]["densify"]["max_screen_fraction"]
    saved["train"]["densify"].update(opacity_reset_interval=1000, max_screen_size=20.0)
    del saved["train"]["data"]["extent"]                  # (from before data.extent: the cameras' spread)
    # (from before the empty-background rules and screen_prune_span: neither, a prune in every densification)
    del saved["train"]["densify"]["empty_background"], saved["train"]["densify"]["screen_prune_span"]
    (tmp_path / "config.json").write_text(json.dumps(saved))
    old = run_folder.RunRecord.read(tmp_path, "missing").train
    assert old.mcmc == config.MCMCConfig()
    assert old.densify.prune_large_after == 1000 and old.densify.max_screen_fraction == 0
    assert old.densify.empty_background == "off" and old.densify.screen_prune_span == 0
    assert cfg.densify.empty_background == "auto" and cfg.densify.screen_prune_span == 500
    assert old.data.extent == "cameras" and cfg.data.extent == "depth"
    with pytest.raises(config.SettingError, match="data.extent.*'rig' is not one of scene, cameras, depth"):
        cfg.with_settings(["data.extent=rig"])


# ---------------------------------------------------------------------------------------------- private names
#: A private module may be imported by the test of that module (it is what the test is about).
PRIVATE_MODULE_TESTS = {("tests/test_packaging.py", "mi_gaussians._libllvm")}


def private_uses(path: Path) -> list[str]:
    """``from mi_gaussians.x import _name``, ``import mi_gaussians.x._y`` and ``module._name`` of an imported package
    module, in the Python file ``path``."""
    tree = ast.parse(path.read_text())
    rel = path.relative_to(ROOT).as_posix()
    modules, out = set(), []
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module and node.module.split(".")[0] == "mi_gaussians":
            for a in node.names:
                target = f"{node.module}.{a.name}"
                if a.name.startswith("_") and (rel, target) not in PRIVATE_MODULE_TESTS:
                    out.append(f"{rel}:{node.lineno}: {target}")
                modules.add(a.asname or a.name)
        elif isinstance(node, ast.Import):
            for a in node.names:
                if a.name.split(".")[0] == "mi_gaussians":
                    if any(p.startswith("_") for p in a.name.split(".")):
                        out.append(f"{rel}:{node.lineno}: {a.name}")
                    modules.add(a.asname or a.name.split(".")[0])
    for node in ast.walk(tree):
        if (isinstance(node, ast.Attribute) and node.attr.startswith("_") and not node.attr.startswith("__")
                and isinstance(node.value, ast.Name) and node.value.id in modules | {"mig"}):
            out.append(f"{rel}:{node.lineno}: {node.value.id}.{node.attr}")
    return out


def test_no_test_or_benchmark_uses_a_private_name_of_the_package():
    files = sorted((ROOT / "tests").rglob("*.py")) + sorted((ROOT / "benchmarks").rglob("*.py"))
    assert len(files) > 30
    bad = [u for f in files for u in private_uses(f)]
    assert not bad, "private names used outside their module:\n" + "\n".join(bad)


def test_self_test_private_uses_are_found(tmp_path, monkeypatch):
    monkeypatch.setitem(globals(), "ROOT", tmp_path)
    (tmp_path / "t.py").write_text("from mi_gaussians.cli import _entries\nfrom mi_gaussians import metrics\n"
                                   "import mi_gaussians.data._x\nmetrics._ssim(1)\nmetrics.ssim(1)\n")
    assert private_uses(tmp_path / "t.py") == ["t.py:1: mi_gaussians.cli._entries", "t.py:3: mi_gaussians.data._x",
                                               "t.py:4: metrics._ssim"]
