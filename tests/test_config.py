"""tacest/configs/estimate.toml (shipped in the package) against the settings dataclasses, and the config errors.

The shipped TOML must list every key of :class:`EstimatorConfig` at its default value,
each with a comment, so that the file and the code cannot drift apart silently: change
a default in tacest/estimation/config.py and this test tells you to update the file.
"""

import dataclasses
import re
import subprocess
import sys
import tomllib
from pathlib import Path

import numpy as np
import pytest

from tacest.errors import TacestError
from tacest.estimation.config import EstimatorConfig, load_config
from tacest.io.run import Run, write_run

ROOT = Path(__file__).resolve().parents[1]
CONFIG = ROOT / "tacest" / "configs" / "estimate.toml"
TACEST = str(Path(sys.executable).parent / "tacest")


def _sections():
    """{section name: dataclass instance with defaults} of EstimatorConfig."""
    cfg = EstimatorConfig()
    return {f.name: getattr(cfg, f.name) for f in dataclasses.fields(cfg)}


# ---------------------------------------------------------------------------------
# the shipped file


def test_shipped_config_loads_and_equals_the_defaults():
    assert load_config(CONFIG) == EstimatorConfig()


def test_shipped_config_lists_every_key_with_its_default():
    # load_config fills left-out keys with defaults, so compare the raw TOML too:
    # every section and key present, nothing extra, each value equal to the default
    raw = tomllib.loads(CONFIG.read_text())
    sections = _sections()
    assert set(raw) == set(sections), "sections of tacest/configs/estimate.toml differ from EstimatorConfig"
    for name, default in sections.items():
        fields = {f.name: getattr(default, f.name) for f in dataclasses.fields(default)}
        missing = sorted(set(fields) - set(raw[name]))
        extra = sorted(set(raw[name]) - set(fields))
        assert not missing, f"[{name}] lacks {missing} in tacest/configs/estimate.toml"
        assert not extra, f"[{name}] has keys {extra} that EstimatorConfig does not know"
        for key, value in fields.items():
            if isinstance(value, tuple):  # frozen settings hold lists as tuples
                value = [list(v) if isinstance(v, tuple) else v for v in value]
            assert raw[name][key] == value, (
                f"tacest/configs/estimate.toml [{name}] {key} = {raw[name][key]!r} but the default is {value!r}")
            assert type(raw[name][key]) is type(value) or isinstance(value, float), (
                f"[{name}] {key}: TOML type {type(raw[name][key]).__name__}, default {type(value).__name__}")


def test_every_key_in_the_shipped_config_has_a_comment():
    section = None
    for line in CONFIG.read_text().splitlines():
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        m = re.fullmatch(r"\[(\w+)\]", s)
        if m:
            section = m.group(1)
            continue
        key = s.split("=", 1)[0].strip()
        assert "#" in s.split("=", 1)[1], f"[{section}] {key} has no comment in tacest/configs/estimate.toml"


def test_the_complementarity_reach_may_be_off_or_on(tmp_path):
    """0 switches the reach off (the only noise key that may be 0); > 0 is a reach in m."""
    for value in (0.0, 0.01):
        assert load_config(_write(tmp_path, f"[noise]\ncomplementarity_reach = {value}\n")).noise.complementarity_reach \
            == value


def test_no_config_means_defaults():
    assert load_config(None) == EstimatorConfig()


def test_a_partial_config_keeps_the_other_defaults(tmp_path):
    p = tmp_path / "partial.toml"
    p.write_text("[noise]\nforce = 0.1\n[solver]\nmax_iter = 50\n")
    cfg = load_config(p)
    assert cfg.noise.force == 0.1 and cfg.solver.max_iter == 50
    assert cfg.noise.normal == EstimatorConfig().noise.normal
    assert cfg.prior == EstimatorConfig().prior


# ---------------------------------------------------------------------------------
# errors: each one a TacestError with a message naming the problem


def _write(tmp_path, text):
    p = tmp_path / "bad.toml"
    p.write_text(text)
    return p


@pytest.mark.parametrize("text,fragments", [
    ("[noise]\nforse = 0.1\n", ["noise", "unknown key", "forse", "valid:", "force"]),
    ("[nois]\nforce = 0.1\n", ["unknown key", "nois", "valid:", "noise"]),
    ("[solver]\nmax_iters = 10\n", ["solver", "unknown key", "max_iters"]),
])
def test_unknown_key_is_an_error(tmp_path, text, fragments):
    _assert_one_line_error(tmp_path, text, fragments)


@pytest.mark.parametrize("text,fragments", [
    ('[noise]\nforce = "big"\n', ["noise.force", "expected a number", "big"]),
    ("[solver]\nprint_every = true\n", ["solver.print_every", "expected an integer"]),
    ("noise = 3\n", ["noise", "expected a table"]),
    ('[solver]\nhessian = "newton"\n', ["solver.hessian", "newton"]),
    ("[solver]\nhessian = 2\n", ["solver.hessian"]),
    ('[solver]\nlinear_solver = "pardiso"\n', ["solver.linear_solver", "pardiso"]),
    ("[solver]\nbarrier = 0.0\n", ["solver.barrier", "(0, 1)"]),
    ("[solver]\nbarrier = 2.0\n", ["solver.barrier", "(0, 1)"]),
    ("[solver]\nbarrier = nan\n", ["solver.barrier", "nan"]),
    ("[solver]\nhomotopy = [[1.0, 2.0]]\n", ["solver.homotopy", "triples"]),
    ("[solver]\nhomotopy = []\n", ["solver.homotopy"]),
    ("[noise]\ncomplementarity_reach = -0.01\n", ["noise.complementarity_reach", "must be >= 0"]),
    ("[noise]\npenetration = 0.0\n", ["noise.penetration", "must be > 0"]),
])
def test_wrong_type_is_an_error(tmp_path, text, fragments):
    _assert_one_line_error(tmp_path, text, fragments)


def _assert_one_line_error(tmp_path, text, fragments):
    """Loading the TOML text raises one TacestError line containing every fragment."""
    p = _write(tmp_path, text)
    with pytest.raises(TacestError) as exc:
        load_config(p)
    msg = str(exc.value)
    assert "\n" not in msg
    for frag in fragments:
        assert frag in msg, msg


# Found while writing these tests (tacest/estimation/config.py belongs to the
# estimation work).
def test_homotopy_not_a_list_is_an_error(tmp_path):
    with pytest.raises(TacestError, match="homotopy"):
        load_config(_write(tmp_path, "[solver]\nhomotopy = 3\n"))


def test_homotopy_with_strings_is_an_error(tmp_path):
    with pytest.raises(TacestError, match="homotopy"):
        load_config(_write(tmp_path, '[solver]\nhomotopy = [["a", 1.0, 1.0]]\n'))


def test_fractional_integer_setting_is_an_error(tmp_path):
    with pytest.raises(TacestError, match="max_iter"):
        load_config(_write(tmp_path, "[solver]\nmax_iter = 1.5\n"))


@pytest.mark.parametrize("text", [
    "[noise\nforce = 0.1\n",
    "[noise]\nforce = \n",
    "[noise]\nforce = 0.1\nforce = 0.2\n",
    "this is not toml\n",
])
def test_invalid_toml_is_an_error(tmp_path, text):
    p = _write(tmp_path, text)
    with pytest.raises(TacestError) as exc:
        load_config(p)
    msg = str(exc.value)
    assert str(p) in msg and "not valid TOML" in msg
    assert "\n" not in msg


def test_not_utf8_is_an_error(tmp_path):
    p = tmp_path / "latin1.toml"
    p.write_bytes("[noise]\n# caf\xe9\nforce = 0.1\n".encode("latin-1"))
    with pytest.raises(TacestError, match="not valid TOML"):
        load_config(p)


def test_missing_config_file_is_an_error(tmp_path):
    with pytest.raises(TacestError, match="no such config file"):
        load_config(tmp_path / "nope.toml")


# ---------------------------------------------------------------------------------
# the CLI: a bad --config is one line on stderr and exit status 2


def _tiny_run(path):
    """A valid 5-sample run file: one finger hovering, never touching."""
    T = 5
    run = Run(dim=2, dt=0.01, time=np.arange(T) * 0.01, gravity=np.array([0.0, -9.81]), source="test",
              finger_position=np.tile([[[0.0, 0.2]]], (T, 1, 1)), finger_radius=np.array([0.01]),
              contact=np.zeros((T, 1), np.uint8), normal=np.full((T, 1, 2), np.nan),
              force=np.zeros((T, 1, 2)))
    write_run(run, path)
    return path


@pytest.mark.parametrize("text,fragment", [
    ("[noise]\nforse = 0.1\n", "unknown key(s) forse"),
    ('[noise]\nforce = "big"\n', "expected a number"),
    ("[noise\n", "not valid TOML"),
])
def test_cli_bad_config_exits_2_with_one_line(tmp_path, text, fragment):
    run = _tiny_run(tmp_path / "run.h5")
    bad = _write(tmp_path, text)
    out = tmp_path / "est.h5"
    res = subprocess.run([TACEST, "estimate", str(run), "--config", str(bad), "-o", str(out)],
                         capture_output=True, text=True, timeout=120)
    assert res.returncode == 2, res.stderr
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1, res.stderr
    assert lines[0].startswith("tacest: error:") and fragment in lines[0] and str(bad) in lines[0]
    assert "Traceback" not in res.stderr and res.stdout == ""
    assert not out.exists()
