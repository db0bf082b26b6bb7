import re
from pathlib import Path

import numpy as np
import pytest

from svcode_core.cli import main
from svcode_core.io import read_tiff


@pytest.fixture
def system_json(tiny_system, tmp_path):
    return tiny_system.save(tmp_path / "tiny.json")


def test_simulate_writes_the_documented_files(system_json, tiny_system, tmp_path, capsys):
    out = tmp_path / "sim"
    assert main(["simulate", "--system", str(system_json), "--object", "beads", "--seed", "3",
                 "--out", str(out)]) == 0
    size = tiny_system.sub_view_size
    shapes = {"measurement": tiny_system.sensor_shape, "views": (9, size, size),
              "demixed": (9, size, size), "object": (size, size)}
    for name, shape in shapes.items():
        array, system, meta = read_tiff(out / f"{name}.tif")
        assert array.shape == shape and array.dtype == np.float32
        assert system == tiny_system and meta["seed"] == 3
    assert "simulated 1 frame" in capsys.readouterr().out


def test_simulate_stack_and_image_object(system_json, tiny_system, tmp_path):
    import tifffile

    image = np.zeros((30, 50), np.uint16)
    image[10:20, 20:30] = 1000
    tifffile.imwrite(tmp_path / "picture.tif", image)
    out = tmp_path / "stack"
    assert main(["simulate", "--system", str(system_json), "--object",
                 str(tmp_path / "picture.tif"), "--frames", "3", "--no-noise",
                 "--memory-budget", "0.0001", "--out", str(out)]) == 0  # one term at a time
    measurement, _, _ = read_tiff(out / "measurement.tif")
    assert measurement.shape == (3, *tiny_system.sensor_shape)
    np.testing.assert_array_equal(measurement[0], measurement[2])  # no noise: identical
    obj, _, _ = read_tiff(out / "object.tif")
    assert obj.max() == pytest.approx(1.0) and obj.min() == 0.0


def test_simulate_bad_object_is_a_clear_error(system_json, tmp_path, capsys):
    assert main(["simulate", "--system", str(system_json), "--object", "unicorns",
                 "--out", str(tmp_path / "x")]) == 2
    assert "neither a phantom kind" in capsys.readouterr().err


def test_a_command_builds_only_its_own_parser():
    """``svcode reconstruct`` registers (and imports) only its own sub-command: scipy, the
    phantoms and the training code stay unloaded, a second of start-up saved per run;
    ``svcode --help`` registers none."""
    import subprocess
    import sys

    code = (
        "import sys\n"
        "from svcode_core.cli import COMMANDS, _commands_needed, build_parser\n"
        "assert _commands_needed(['--debug', 'reconstruct', 'x.tif']) == ('reconstruct',)\n"
        "assert _commands_needed(['--help']) == _commands_needed(['recon']) == ()\n"
        "build_parser(_commands_needed(['reconstruct', 'x.tif', '--out', 'y.tif']))\n"
        "loaded = [m for m in ('scipy', 'svcode_core.phantoms', 'svcode_core.training')\n"
        "          if m in sys.modules]\n"
        "print(loaded)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True)  # fmt: skip
    assert out.stdout.strip() == "[]"


#: every command's help: none needs torch, the training loss's SSIM or scikit-image (train
#: and bench read their constants and defaults from torch-free modules)
_LIGHT_HELP = ("", "reconstruct", "simulate", "demo", "dataset", "calibrate", "train", "bench")
_HEAVY = ("torch", "pytorch_msssim", "skimage")


@pytest.mark.parametrize("command", _LIGHT_HELP)
def test_help_imports_no_torch(command):
    """``svcode --help`` and ``svcode COMMAND --help`` start in a fraction of a second, and
    the help lists every option of the command."""
    import subprocess
    import sys

    bare = subprocess.run([sys.executable, "-c", "import sys, svcode_core; "
                           "print('torch' in sys.modules)"], capture_output=True, text=True,
                          check=True)  # fmt: skip
    if bare.stdout.strip() == "True":
        pytest.skip("the svcode_core package itself imports torch")
    argv = [command, "--help"] if command else ["--help"]
    code = (
        "import sys\n"
        "from svcode_core.cli import main\n"
        "try:\n"
        f"    main({argv!r})\n"
        "except SystemExit:\n"
        "    pass\n"
        f"print(sorted(m for m in {_HEAVY!r} if m in sys.modules), file=sys.stderr)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True)  # fmt: skip
    assert "usage: svcode" in out.stdout and out.stderr.strip() == "[]"
    if command:
        assert all(flag in out.stdout for flag in _options(command))


def _options(command: str) -> dict[str, str]:
    """Every option string of ``command`` → its destination."""
    from svcode_core.cli import build_parser

    parser = build_parser((command,))
    [subparsers] = [a for a in parser._actions if a.dest == "command"]
    return {flag: action.dest for flag, action in
            subparsers.choices[command]._option_string_actions.items()}  # fmt: skip


@pytest.mark.parametrize("command", ["simulate", "reconstruct", "demo", "dataset", "train",
                                     "bench", "calibrate"])  # fmt: skip
def test_one_meaning_per_flag(command):
    """A flag means the same in every command that has it; the other name of an option
    (``--preset``, ``--quiet``, ``--objects``) is the same option."""
    options = _options(command)
    assert options["--system"] == options["--preset"] == "system"
    if "--no-progress" in options or "--quiet" in options:
        assert options["--no-progress"] == options["--quiet"] == "no_progress"
    if "--object" in options or "--objects" in options:
        assert options["--object"] == options["--objects"] == "object"
    if command == "train":  # the data loader's processes, not reconstruction's
        assert options["--loader-workers"] == "loader_workers"


def test_every_system_option_takes_a_preset_or_a_file(system_json, tmp_path, capsys):
    for source in (["--preset", "cm2-mini"], ["--system", "cm2-mini"]):
        out = tmp_path / source[0].strip("-")
        assert main(["simulate", *source, "--object", "beads", "--no-noise", "--quiet",
                     "--out", str(out)]) == 0
    assert main(["dataset", "--preset", str(system_json), "--frames", "2", "--objects", "cells",
                 "--quiet", "--out", str(tmp_path / "data")]) == 0
    assert "differs" not in capsys.readouterr().err


def test_train_workers_is_the_deprecated_name_of_loader_workers(tmp_path, capsys):
    args = ["train", "--data", str(tmp_path / "none"), "--out", str(tmp_path / "run")]
    assert main([*args, "--workers", "-1"]) == 2
    err = capsys.readouterr().err
    assert "warning: --workers is the deprecated name of --loader-workers" in err
    assert "error: --loader-workers: must be >= 0, got -1" in err


def test_bench_writes_beside_the_user_not_into_the_checkout(tmp_path, capsys):
    from svcode_core.cli import build_parser
    from svcode_core.cli.bench import CHECKOUT_RESULTS

    args = build_parser(("bench",)).parse_args(["bench"])
    assert args.out == Path("svcode-bench")
    # a partial run into the committed report is refused before any work
    for partial in (["--quick"], ["--regimes", "matched"], ["--methods", "wiener"]):
        assert main(["bench", *partial, "--out", str(CHECKOUT_RESULTS)]) == 2
        err = capsys.readouterr().err
        assert "committed report" in err and "--merge" in err and partial[0] in err


@pytest.mark.parametrize("command, option, message", [
    ("dataset", ["--frames", "1"], "--frames: must be >= 2, got 1"),
    ("dataset", ["--val-fraction", "2"], "--val-fraction: must lie in (0, 1), got 2.0"),
    ("dataset", ["--instrument-frames", "0"], "--instrument-frames: must be >= 1, got 0"),
    ("simulate", ["--memory-budget", "-1"], "--memory-budget must be a positive number of GiB"),
])  # fmt: skip
def test_option_errors_name_the_option_as_given(system_json, tmp_path, capsys, command,
                                                option, message):
    args = [command, "--system", str(system_json), "--out", str(tmp_path / "out")]
    args += ["--frames", "4", "--no-progress"] if command == "dataset" else []
    assert main([*args, *option]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"svcode {command}: error: {message}" in err, err
    assert "_" not in err.split("error: ")[1].split(":")[0]
    assert not (tmp_path / "out").exists()


# ------------------------------------------------- the methods' options, from their tables
def _reconstruct_parser():
    import argparse

    from svcode_core.cli import build_parser

    parser = build_parser()
    commands = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return commands.choices["reconstruct"]


def _table():
    from svcode_core.methods import registry

    return [(name, option) for name in registry.METHODS
            for option in registry.method(name).options]  # fmt: skip


def _sample(option):
    """A value of ``option`` other than its default."""
    if option.kind is bool:
        return not option.default
    if option.choices:
        return next(choice for choice in option.choices if choice != option.default)
    if option.flag_scale != 1:
        return 3 * option.flag_scale
    return option.kind(int(option.minimum or 0) + 2)


def test_every_method_option_has_a_flag_made_from_its_table():
    """Each option of each method's table has its ``svcode reconstruct`` flag (and no flag
    is a method's without an option), with the table's help and default."""
    parser = _reconstruct_parser()
    groups = [group for group in parser._action_groups
              if (group.title or "").startswith("options of --method")]  # fmt: skip
    flags = {flag for group in groups for action in group._group_actions
             for flag in action.option_strings}  # fmt: skip
    assert flags == {option.flag for _, option in _table()}
    text = "".join(parser.format_help().split())  # the help wraps lines at spaces and hyphens
    for name, option in _table():
        assert "".join(option.describe().split()) in text, (name, option.name)
        if option.default is not None and "{default}" in option.help:
            shown = option.default
            if option.flag_scale != 1:  # in the flag's units
                shown //= option.flag_scale
            shown = f"{shown:g}" if isinstance(shown, float) else str(shown)
            assert f"default{shown}" in text.replace(":", ""), (name, option.name)


@pytest.mark.parametrize(("method", "option"), _table(), ids=lambda v: getattr(v, "name", v))
def test_a_flag_gives_its_option_and_is_checked_by_the_table(method, option):
    """A value round-trips through its flag (units converted), and a value out of the
    table's bounds is refused naming the flag, with the table's words."""
    from svcode_core.cli.reconstruct import check_options, method_options

    parser = _reconstruct_parser()
    head = ["in.tif", "--out", "out.tif", "--method", method]
    value = _sample(option)
    args = parser.parse_args([*head, *option.to_flag(value)])
    assert method_options(args) == {option.name: value}
    if option.minimum is None:
        return
    below = str(int(option.minimum) - 1)
    args = parser.parse_args([*head, option.flag, below])
    expected = f"{option.flag} must be {option.words(flag=True)}, got {below}"
    with pytest.raises(ValueError, match=f"^{re.escape(expected)}$"):
        check_options(args)
