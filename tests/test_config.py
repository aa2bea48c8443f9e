"""--config FILE.toml: every option from a file, the command line winning, every mistake named."""
import json
import pathlib

from mpi4py import MPI
import pytest

from face_dolfinx.cli.main import main, parse_arguments, tracking_settings
from face_dolfinx.tracking import PRESETS


@pytest.fixture
def shared_tmp(tmp_path):
    """One temporary folder for all ranks (each rank's tmp_path differs under mpirun)."""
    return pathlib.Path(MPI.COMM_WORLD.bcast(str(tmp_path), root=0))


def write(path: pathlib.Path, text: str) -> pathlib.Path:
    if MPI.COMM_WORLD.rank == 0:
        path.write_text(text)
    MPI.COMM_WORLD.barrier()
    return path


def test_file_under_table_under_command_line(shared_tmp):
    config = write(shared_tmp / "run.toml", """
tets = 7000                 # shared: every subcommand with --tets
out = "results/shared"
verbose = true              # an option of the main parser
[fit]
capture = "takes/session1.c3d"
gn-steps = 5                # dashes ...
neutral_frame = 12          # ... or underscores
correspondence = "session1.toml"
smoothness = 2              # an integer where a number is expected
out = "results/session1"    # the table overrides the top level
[build]
tets = 9000
""")
    args, _ = parse_arguments(["fit", "--config", str(config), "--gn-steps", "2"])
    assert (args.capture, args.gn_steps, args.neutral_frame, args.correspondence) == \
        ("takes/session1.c3d", 2, 12, "session1.toml")
    assert args.smoothness == 2.0 and isinstance(args.smoothness, float)
    assert (args.tets, args.out, args.verbose) == (7000, "results/session1", True)
    assert tracking_settings(args).fit.mode == "exact"
    args, _ = parse_arguments(["fit", "other.trc", "--config", str(config), "--out", "here"])
    assert (args.capture, args.out) == ("other.trc", "here")
    args, _ = parse_arguments(["build", "--config", str(config)])
    assert (args.tets, args.out) == (9000, "results/shared")
    # fit --fast, on the command line or in the file, fills in what neither of them gives.
    from_flag, _ = parse_arguments(["fit", "--config", str(config), "--fast", "--newton-tolerance", "1e-3"])
    fast_file = write(shared_tmp / "fast.toml", "[fit]\ncapture = 't.trc'\nfast = true\ngn-steps = 5\n"
                                                "newton-tolerance = 1e-3\n")
    from_file, _ = parse_arguments(["fit", "--config", str(fast_file)])
    fast = PRESETS["fast"]
    for args in (from_flag, from_file):
        settings = tracking_settings(args)
        assert (settings.fit.max_gn_steps, settings.newton_tolerance) == (5, 1e-3)
        assert (settings.reuse_factorization, settings.refresh_contraction, settings.fit.approximate_jacobian_within) \
            == (fast.reuse_factorization, fast.refresh_contraction, fast.fit.approximate_jacobian_within) \
            == (True, 0.5, 1.0)
        assert settings.line_search_iterations == fast.line_search_iterations == 3
    settings = tracking_settings(parse_arguments(["fit", "take.trc"])[0])
    assert (settings.reuse_factorization, settings.fit.approximate_jacobian_within, settings.fit.max_gn_steps) \
        == (False, 0.0, 3)
    assert settings.line_search_iterations == 1
    args, _ = parse_arguments(["build", "--config", str(config), "--tets", "3000"])
    assert args.tets == 3000


def test_flags_and_lists(shared_tmp):
    config = write(shared_tmp / "simulate.toml", """
[simulate]
expressions = ["smile", "frown"]
no-render = true
degree = 2
""")
    args, _ = parse_arguments(["simulate", "--config", str(config)])
    assert (args.expressions, args.no_render, args.degree) == (["smile", "frown"], True, 2)
    args, _ = parse_arguments(["simulate", "pucker", "--config", str(config)])
    assert args.expressions == ["pucker"]


@pytest.mark.parametrize("text, message", [
    ("[fit]\ngn_stepz = 3\n", r"bad\.toml: unknown key 'gn_stepz' in \[fit\] \(did you mean 'gn-steps'\?\)"),
    ("[build]\nscenario = 'smile'\n", r"bad\.toml: unknown key 'scenario' in \[build\]; build takes: .*tets"),
    ("colour = 'red'\n", r"bad\.toml: unknown key 'colour' \(not an option of any subcommand\)"),
    ("[fitt]\nmode = 'exact'\n", r"bad\.toml: unknown table \[fitt\] \(did you mean 'fit'\?\)"),
    ("[fit]\ngn-steps = 2.5\n", r"bad\.toml: \[fit\] gn-steps must be an integer, not 2\.5"),
    ("[fit]\nmode = 'fast'\n", r"bad\.toml: \[fit\] mode = 'fast': expected one of exact, paper"),
    ("[fit]\noverwrite = 'yes'\n", r"bad\.toml: \[fit\] overwrite must be true or false"),
    ("[fit]\ngn-steps = 2\ngn_steps = 3\n", r"bad\.toml: \[fit\] sets 'gn-steps' twice \('gn-steps' and 'gn_steps'\)"),
    ("tets = 'many'\n", r"bad\.toml: tets must be an integer, not 'many'"),
    ("[fit]\nneutral-frame = 'rest'\n", r"bad\.toml: \[fit\] neutral-frame: 'rest': give a frame number or 'typical'"),
    ("[fit]\nneutral-frame = 2.5\n", r"bad\.toml: \[fit\] neutral-frame: '2\.5': give a frame number or 'typical'"),
    ("[fit]\nstrength = [2]\n", r"bad\.toml: \[fit\] strength must be a number or a word, not \[2\]"),
    ("[fit]\nstrength = 'mentalis_left=0'\n", r"bad\.toml: \[fit\] strength: 'mentalis_left=0': a strength factor must be positive"),
    ("[fit]\nconfig = 'other.toml'\n", r"bad\.toml: unknown key 'config' in \[fit\]"),
    ("[fit\n", r"bad\.toml: malformed TOML"),
])
def test_mistakes_are_named(shared_tmp, text, message):
    """Checked whichever subcommand runs: a typo in [fit] stops `build` too."""
    config = write(shared_tmp / "bad.toml", text)
    for command in (["fit", "take.trc"], ["build"]):
        with pytest.raises(SystemExit, match=message):
            main([*command, "--config", str(config)])


def test_the_documented_example(shared_tmp):
    """docs/cli.md's example is a valid file for every subcommand."""
    document = (pathlib.Path(__file__).resolve().parents[1] / "docs" / "cli.md").read_text()
    example = document.split("```toml\n", 1)[1].split("```", 1)[0]
    config = write(shared_tmp / "session.toml", example)
    args, _ = parse_arguments(["fit", "--config", str(config)])
    assert (args.model, args.neutral_frame, args.units, args.tets) == ("models/subject01", 10, "mm", 20000)
    args, _ = parse_arguments(["build", "--config", str(config)])
    assert (args.subject, args.out, args.model) == ("captures/session01/neutral.c3d", "models/subject01", None)
    for command in (["simulate", "smile"], ["synth"], ["demo"]):
        parse_arguments([*command, "--config", str(config)])


def test_missing_or_wrong_config_file(shared_tmp):
    with pytest.raises(SystemExit, match=r"absent\.toml: no such configuration file"):
        main(["build", "--config", str(shared_tmp / "absent.toml")])
    with pytest.raises(SystemExit, match=r"run\.json: a configuration file must be TOML"):
        main(["build", "--config", str(write(shared_tmp / "run.json", "{}"))])


def test_required_positional_from_neither(shared_tmp, capsys):
    config = write(shared_tmp / "empty.toml", "[fit]\ngn-steps = 2\n")
    with pytest.raises(SystemExit) as stop:
        main(["fit", "--config", str(config)])
    assert stop.value.code == 2
    assert "the capture argument is required (on the command line or as 'capture' in the --config file)" \
        in capsys.readouterr().err


def test_a_run_from_a_config_file(builtin_model_path, shared_tmp):
    out = shared_tmp / "from_config"
    config = write(shared_tmp / "simulate.toml", f"""
model = "{builtin_model_path}"
[simulate]
expressions = ["smile"]
out = "{out}"
no_render = true
""")
    assert main(["simulate", "--config", str(config)]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert [row["expression"] for row in summary["expressions"]] == ["smile"]
    assert summary["model"] == str(builtin_model_path)
    assert not (out / "01_smile.png").exists()  # no_render came from the file
