"""Tracking settings and presets: one table between the fit command, the run record and the library."""
import csv
import dataclasses
import json

from mpi4py import MPI
import numpy as np
import pytest

from face_dolfinx.cli.main import main, parse_arguments, tracking_settings
from face_dolfinx.fitting import FitSettings
from face_dolfinx.tracking import PRESETS, RECORD_FIELDS, SettingError, Tracker, TrackingSettings

# A value other than the default for every setting, as the command line gives it and as it is kept.
OTHER_VALUES = dict(mode=("paper", "paper"), gn_steps=("5", 5), smoothness=("0.5", 0.5), effort=("2", 2.0),
                    intraoral_pressure=(None, True), pressure_limit=("50", 50.0),
                    fresh_jacobians=("2", 2), approximate_jacobians=("0.1", 0.1),
                    reuse_factorization=(None, True), newton_tolerance=("1e-3", 1e-3),
                    newton_energy_tolerance=("5", 5.0),
                    refresh_contraction=("0.3", 0.3), line_search_iterations=("2", 2), contact=(None, True),
                    krylov=(None, True), contact_relaxation=(None, True))
# Settings that need another one changed with them.
NEEDS = dict(krylov=("reuse_factorization", "--reuse-factorization"))


def test_every_setting_is_a_fit_option_of_the_same_name():
    assert set(OTHER_VALUES) == set(RECORD_FIELDS)
    default = PRESETS["default"]
    for key, (text, value) in OTHER_VALUES.items():
        assert default.value(key) != value
        option = [f"--{key.replace('_', '-')}"] + ([text] if text is not None else [])
        changed = {key}
        if key in NEEDS:
            changed.add(NEEDS[key][0])
            option.append(NEEDS[key][1])
        settings = tracking_settings(parse_arguments(["fit", "take.trc", *option])[0])
        assert settings.value(key) == value
        assert {k: v for k, v in settings.record().items() if k not in changed} == \
            {k: v for k, v in default.record().items() if k not in changed}


def test_krylov_without_a_kept_factor_is_refused():
    with pytest.raises(SettingError, match="needs reuse_factorization"):
        PRESETS["default"].updated(dict(krylov=True))
    with pytest.raises(SystemExit, match="--krylov True: Krylov on the old factor needs reuse_factorization"):
        tracking_settings(parse_arguments(["fit", "take.trc", "--krylov"])[0])
    assert PRESETS["fast"].updated(dict(krylov=True)).problem_options()["krylov_on_old_factor"]


def test_default_preset_is_the_library_default_and_fast_differs_where_documented():
    assert PRESETS["default"] == TrackingSettings(FitSettings())
    fast = PRESETS["fast"]
    changed = {key for key in RECORD_FIELDS if fast.value(key) != PRESETS["default"].value(key)}
    assert changed == {"gn_steps", "fresh_jacobians", "approximate_jacobians", "reuse_factorization",
                       "newton_tolerance", "newton_energy_tolerance", "refresh_contraction",
                       "line_search_iterations"}
    assert fast.problem_options() == dict(reuse_factorization=True, refresh_contraction=0.5,
                                          newton_tolerance=1e-2, newton_energy_tolerance=100.0,
                                          line_search_iterations=3, krylov_on_old_factor=False,
                                          intraoral_pressure=False, lip_contact=None, contact=None,
                                          contact_relaxation=None)


def test_updated_keeps_what_is_none_and_leaves_the_preset_alone():
    fast = PRESETS["fast"]
    settings = fast.updated(dict(gn_steps=4, newton_tolerance=None, mode=None))
    assert settings.fit.max_gn_steps == 4 and settings.newton_tolerance == fast.newton_tolerance
    assert fast.fit.max_gn_steps == 2  # presets are not changed by their variants
    assert dataclasses.replace(settings, fit=dataclasses.replace(settings.fit, max_gn_steps=2)) == fast


@pytest.mark.parametrize("key, value, requirement", [
    ("newton_tolerance", 0.0, "give a positive distance in mm"),
    ("newton_energy_tolerance", -1.0, "give a positive energy in mN mm"),
    ("refresh_contraction", 1.0, "give a factor between 0 and 1"),
    ("line_search_iterations", 0, "give 1 or more"),
    ("fresh_jacobians", -1, "give 0 or more fresh Jacobians per frame"),
    ("approximate_jacobians", -0.5, "give a distance in mm, 0 or more"),
    ("gn_steps", 0, "give 1 or more Gauss-Newton steps per frame"),
    ("mode", "linear", "use exact or paper"),
])
def test_out_of_range_settings_are_refused_naming_the_setting(key, value, requirement):
    with pytest.raises(SettingError) as refused:
        PRESETS["default"].updated({key: value})
    assert (refused.value.key, refused.value.value, refused.value.requirement) == (key, value, requirement)
    if key == "mode":  # the command line offers only the valid choices
        return
    option = f"--{key.replace('_', '-')}"
    with pytest.raises(SystemExit, match=f"{option} {value}: {requirement}"):
        tracking_settings(parse_arguments(["fit", "take.trc", option, str(value)])[0])


def test_rank_groups_beyond_the_ranks_are_refused(model):
    with pytest.raises(ValueError, match="rank_groups = 0"):
        Tracker(model, rank_groups=0)
    with pytest.raises(ValueError, match="the number of ranks"):
        Tracker(model, rank_groups=model.mesh.comm.size + 1)


def test_part_of_a_take_with_validation_markers(builtin_model_path, shared_dir):
    """fit --frames START:STOP:STEP fits those frames of the take (numbered as in the take), and
    --validation-markers N leaves N markers out of the fit, measured in frames.csv and accuracy.json."""
    model = ["--model", str(builtin_model_path)]
    take = shared_dir / "part" / "take.trc"
    assert main(["synth", *model, "--frames", "8", "--noise", "0.3", "--out", str(take)]) == 0
    out = shared_dir / "part" / "fit"
    assert main(["fit", str(take), *model, "--out", str(out), "--frames", "1:8:3", "--validation-markers", "3"]) == 0
    with open(out / "frames.csv") as table:
        rows = list(csv.DictReader(table))
    assert [int(row["take_frame"]) for row in rows] == [1, 4, 7]
    record = json.loads((out / "accuracy.json").read_text())
    assert record["roles"]["validation"]["markers"] == 3
    validation = [name for name, marker in record["markers"].items() if marker["role"] == "validation"]
    # Over the take the markers move far beyond the 0.3 mm noise (4-5 mm RMS beyond the head's
    # motion); the fit follows them, the left-out ones included, to about the noise.
    for role in ("fitted", "validation"):
        pooled = record["roles"][role]
        assert pooled["non_rigid_mm"] > 2.0 and pooled["rms_mm"] < 0.5 and pooled["explained"] > 0.95
    for row in rows:
        assert float(row["validation_rms_mm"]) < 0.5
    errors = np.genfromtxt(out / "marker_errors.csv", delimiter=",", names=True)
    assert all(np.all(np.isfinite(errors[name])) for name in validation)  # followed, reported
    run = json.loads((out / "run.json").read_text())
    assert run["marker_setup"]["validation"] == 3 and run["take_frame_selection"] == "1:8:3"


@pytest.mark.parametrize("options, message", [
    (["--validation-markers", "forehead_1,nowhere"], "validation names marker 'nowhere'"),
    (["--frames", "9:12"], "--frames 9:12: no frame of the 8-frame take"),
    (["--frames", "2"], "--frames 2: give START:STOP or START:STOP:STEP"),
    (["--frames", "0:8:0"], "the step must be 1 or more"),
    (["--effort", "-1"], "--effort -1.0: give a weight, 0 or more"),
])
def test_bad_part_and_marker_options_leave_nothing(builtin_model_path, shared_dir, options, message):
    model = ["--model", str(builtin_model_path)]
    take = shared_dir / "bad" / "take.trc"
    if not take.exists():
        assert main(["synth", *model, "--frames", "8", "--out", str(take), "--overwrite"]) == 0
    out = shared_dir / "bad" / "never"
    with pytest.raises(SystemExit, match=message):
        main(["fit", str(take), *model, "--out", str(out), *options])
    assert not out.exists()


def test_a_fit_folder_without_contact_settings_resumes_without_contact(builtin_model_path, shared_dir):
    """A fit folder whose run.json has no ``contact`` and ``contact_surfaces`` (written before the
    fit recorded them) resumes as a fit without contact; with --contact it is refused, naming the
    folder and the difference, before any frame is fitted."""
    model = ["--model", str(builtin_model_path)]
    take = shared_dir / "old" / "take.trc"
    assert main(["synth", *model, "--frames", "3", "--out", str(take)]) == 0
    out = shared_dir / "old" / "fit"
    assert main(["fit", str(take), *model, "--out", str(out), "--stop-after", "1"]) == 0
    record = json.loads((out / "run.json").read_text())
    MPI.COMM_WORLD.barrier()  # every rank has read it before rank 0 rewrites it
    if MPI.COMM_WORLD.rank == 0:
        (out / "run.json").write_text(json.dumps({k: v for k, v in record.items()
                                                  if k not in ("contact", "contact_surfaces")}))
    MPI.COMM_WORLD.barrier()
    message = (rf"{out} holds an unfinished fit with other settings \(contact: False there, True now; "
               r"contact_surfaces: \[\] there, \['lips', 'teeth'\] now\); pass --overwrite")
    with pytest.raises(SystemExit, match=message):
        main(["fit", str(take), *model, "--out", str(out), "--contact"])
    assert sorted(p.name for p in (out / "frames").glob("*.json")) == ["000000.json"]
    assert main(["fit", str(take), *model, "--out", str(out)]) == 0
    assert not (out / "IN_PROGRESS").exists() and len(list((out / "frames").glob("*.json"))) == 3
    assert json.loads((out / "run.json").read_text()) == record
