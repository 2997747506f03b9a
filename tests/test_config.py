"""The config file: values of the wrong TOML type are refused (exit status 2), never converted."""

from pathlib import Path

import pytest

from facepipe.errors import InputError
from facepipe.io.config import load_config
from facepipe.sample_rig import write_sample_rig
from tests.conftest import run_cli

# (table, key = value as written, the fix the hint gives)
WRONG_TYPES = [
    ("psd", "max_poses = 12.7", "write an integer, e.g. max_poses = 12"),  # a float for an integer
    ("psd", "max_poses = 12.0", "write max_poses = 12"),
    ("psd", "greedy_vertices = true", "write an integer"),  # a boolean is no integer
    ("shell", 'k_bend = "0.5"', "write k_bend = 0.5"),  # a string for a number
    ("shell", "k_stretch = true", "write a number, e.g. k_stretch = 0.0"),  # a boolean is no number
    ("shell", "phantoms = 3.5", "write an integer"),
    ("shell", "method = 3", 'write method = "3"'),  # a number for a string
    ("tune", 'k_stretch = "0.1, 0.3"', "write k_stretch = [0.1, 0.3]"),  # a string for a list
    ("tune", "beta_scale = 1.0", "write beta_scale = [1.0]"),  # a number for a list
    ("tune", 'smoothing = [0.0, "0.1"]', "write smoothing = [0.0, 0.1]"),  # a string in a list of numbers
    ("tune", "novelty_tau = [true]", "write a list of numbers"),
    ("tune", 'fallback = "no"', "write fallback = false"),  # bool("no") would be true
    ("tune", "fallback = 1", "write fallback = true"),
    ("tune", "folds = 3.0", "write folds = 3"),
    ("examples", "sequence_stride = 2.5", "write an integer"),
    ("examples", "meshes = 3", "write meshes = [\"3\"]"),
    ("rig", "units = 1", 'write units = "1"'),
    ("features", "graph = false", 'write graph = "false"'),
]


@pytest.fixture(scope="module")
def sample(tmp_path_factory):
    """A small sample rig: its config is valid, so every error below is the one value's."""
    return write_sample_rig(tmp_path_factory.mktemp("config_rig"), n_vertices=2000, n_examples=3, n_frames=4)


def with_value(sample, tmp_path, table: str, line: str) -> Path:
    """The sample config with ``line`` added to ``[table]`` (the table added when it has none)."""
    text = Path(sample["config"]).read_text(encoding="utf-8")
    text = text.replace(f"[{table}]\n", f"[{table}]\n{line}\n") if f"[{table}]\n" in text \
        else text + f"\n[{table}]\n{line}\n"
    key = line.split("=")[0].strip()
    # the key replaces its line in the sample config, if it has one (TOML forbids a key twice)
    lines = text.splitlines()
    first = lines.index(line)
    lines = [s for i, s in enumerate(lines) if i <= first or s.split("=")[0].strip() != key]
    cfg = Path(sample["config"]).parent / f"wrong_{tmp_path.name}.toml"
    cfg.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return cfg


@pytest.mark.parametrize("table, line, fix", WRONG_TYPES)
def test_wrong_type_is_refused_naming_file_key_value_type_and_fix(sample, tmp_path, table, line, fix):
    cfg = with_value(sample, tmp_path, table, line)
    key, value = (s.strip() for s in line.split("=", 1))
    with pytest.raises(InputError) as exc:
        load_config(cfg)
    message = str(exc.value)
    assert str(cfg) in message and f"[{table}] {key} = {value}" in message, message
    assert "expected " in message and fix in message, message


@pytest.mark.parametrize("table, line, fix", WRONG_TYPES)
def test_wrong_type_through_the_cli_exits_2_without_output(sample, tmp_path, capsys, table, line, fix):
    cfg = with_value(sample, tmp_path, table, line)
    out = tmp_path / "fit.npz"
    assert run_cli("fit", cfg, "-o", out) == 2
    err = capsys.readouterr().err
    assert str(cfg) in err and fix in err, err
    assert not list(tmp_path.iterdir()), "fit wrote something"
    assert run_cli("bake", cfg, "-o", tmp_path / "model.npz") == 2
    assert fix in capsys.readouterr().err
    assert not list(tmp_path.iterdir()), "bake wrote something"


def test_right_types_are_read_as_before(sample, tmp_path):
    """An integer for a number is that number; lists of integers, booleans and strings as written."""
    cfg = with_value(sample, tmp_path, "shell", "k_bend = 2")
    text = cfg.read_text(encoding="utf-8") + ("\n[tune]\nk_stretch = [0, 1]\nfallback = false\nmax_regression = 0\n"
                                              'vertices = "0:10"\n')
    cfg.write_text(text, encoding="utf-8")
    config = load_config(cfg)
    assert config.shell.k_bend == 2.0 and isinstance(config.shell.k_bend, float)
    assert isinstance(config.tune.max_regression, float)
    assert config.tune.k_stretch == [0, 1] and config.tune.fallback is False and config.tune.vertices == "0:10"
    assert config.psd.max_poses == 3 and config.units == "cm"


def test_a_table_written_as_a_value_is_refused(sample, tmp_path):
    cfg = tmp_path / "flat.toml"
    cfg.write_text('tune = 3\n[rig]\nmesh = "neutral.obj"\nmarkers = "markers.csv"\n', encoding="utf-8")
    with pytest.raises(InputError, match=r"tune = 3 is an integer, expected the table \[tune\]"):
        load_config(cfg)


def test_sequence_stride_below_one_is_refused(sample, tmp_path):
    cfg = with_value(sample, tmp_path, "examples", "sequence_stride = 0")
    with pytest.raises(InputError, match=r"\[examples\] sequence_stride = 0 must be ≥ 1"):
        load_config(cfg)


def with_sequence(sample, tmp_path, line: str) -> Path:
    """The sample config with its take's truth as the example sequence and ``line`` after it."""
    text = Path(sample["config"]).read_text(encoding="utf-8")
    cfg = Path(sample["config"]).parent / f"seq_{tmp_path.name}.toml"
    cfg.write_text(text.replace('sequence = ""', f'sequence = "take_truth.npz"\n{line}'), encoding="utf-8")
    return cfg


@pytest.mark.parametrize("line, fix", [
    ('sequence_frames = "0:80"', "e.g. sequence_frames = [0, 80]"),  # a string for a list
    ("sequence_frames = [0, 80.0]", "write sequence_frames = [0, 80]"),  # a float is no frame
    ("sequence_frames = [80, 10]", "e.g. sequence_frames = [0, 80]"),  # first ≥ stop
    ("sequence_frames = [-1, 10]", "e.g. sequence_frames = [0, 80]"),
    ("sequence_frames = [0, 10, 20]", "e.g. sequence_frames = [0, 80]"),
])
def test_sequence_frames_must_be_a_frame_range(sample, tmp_path, line, fix):
    cfg = with_sequence(sample, tmp_path, line)
    with pytest.raises(InputError, match=r"\[examples\] sequence_frames") as err:
        load_config(cfg)
    assert fix in str(err.value)


def test_sequence_frames_without_a_sequence_is_refused(sample, tmp_path):
    cfg = with_value(sample, tmp_path, "examples", "sequence_frames = [0, 2]")
    with pytest.raises(InputError, match=r"sequence_frames = \[0, 2\] without a sequence"):
        load_config(cfg)


def test_sequence_frames_select_the_training_rows(sample, tmp_path):
    """Rows first … stop − 1 of the sequence file are the examples, named by their row; a stop
    past the take's end names the take's length."""
    from facepipe.pipeline.rig import load_rig

    cfg = with_sequence(sample, tmp_path, "sequence_frames = [1, 3]")
    rig = load_rig(cfg)
    seq_names = [n for n in rig.example_names if n.startswith("take_truth:")]
    assert seq_names == ["take_truth:1", "take_truth:2"]
    cfg = with_sequence(sample, tmp_path, "sequence_frames = [1, 99]")
    with pytest.raises(InputError, match=r"reaches past the sequence's 4 frames"):
        load_rig(cfg)


@pytest.mark.parametrize("row, expected", [
    ("nose,12x", r"line 4: marker 'nose' has vertex '12x', not an integer"),
    ("nose,99999999999999999999999", r"line 4: marker 'nose' has vertex 99999999999999999999999, past any mesh"),
    ("nose,-5", r"line 4.*vertex -5"),
    ("chin,7", r"line 4: marker name 'chin' appears twice"),
    ("nose,12,wobble", r"line 4: marker 'nose' has role 'wobble'"),
])
def test_markers_file_errors_name_the_line(tmp_path, row, expected):
    """Every bad row of a markers file is an input error naming its line, an index far past the
    64-bit range included (it was an OverflowError)."""
    from facepipe.pipeline.rig import load_markers

    path = tmp_path / "markers.csv"
    path.write_text("name,vertex,role\nchin,7\nbrow,9,stable\n" + row + "\nlip,3\n")
    with pytest.raises(InputError, match=expected):
        load_markers(path, 100)


@pytest.mark.parametrize("line", ["rcond = -1e-4", "rcond = 1.0", "rcond = 5.0"])
def test_rbf_cut_off_outside_its_range_is_refused(sample, tmp_path, capsys, line):
    cfg = with_value(sample, tmp_path, "psd", line)
    with pytest.raises(InputError, match=r"(?s)\[psd\] rcond = .*0 ≤ rcond < 1") as exc:
        load_config(cfg)
    assert str(cfg) in str(exc.value)
    assert run_cli("bake", cfg, "-o", tmp_path / "model.npz") == 2  # before any work, nothing written
    assert "0 ≤ rcond < 1" in capsys.readouterr().err
    assert not list(tmp_path.iterdir()), "bake wrote something"


@pytest.mark.parametrize("text", ["1\n2\n3\n", "3\r\n1\r\n2\r\n", "5\n4", "007\n8\n", "4\n4\n", "1\n\n2\n", " 1\n2\n",
                                  "1 2\n", "1\n99\n", "", "\n", "1\n# neck\n", "-1\n", "1.5\n", "1\n2\n\n",
                                  "99999999999999999999999\n", "x\n"])
def test_anchors_read_whole_or_line_by_line_alike(tmp_path, monkeypatch, text):
    """A plain anchors file (one index a line) is read in one piece; anything else line by line,
    which names the line at fault: both give the same indices, or the same error."""
    import facepipe.pipeline.rig as rig

    path = tmp_path / "anchors.txt"
    path.write_text(text)

    def read():
        try:
            return rig.load_anchors(path, 10).tolist()
        except InputError as exc:
            return str(exc)

    whole = read()
    plain = text in ("1\n2\n3\n", "3\r\n1\r\n2\r\n", "5\n4", "007\n8\n", "4\n4\n")
    assert (rig._plain_indices(path.read_bytes(), 10) is not None) == plain  # the plain ones in one piece
    monkeypatch.setattr(rig, "_plain_indices", lambda data, n: None)
    assert read() == whole
