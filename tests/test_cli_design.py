import json

import pytest

import moirejax as mj
from moirejax.cli._main import main


@pytest.mark.parametrize("name, A, d_eff", [("dense", 4.00, 0.25), ("mid", 14.00, 0.10), ("sparse", 24.00, 0.07)])
def test_design_json_reproduces_paper_table(capsys, name, A, d_eff):
    assert main(["design", "--preset", name, "--json"]) == 0
    table = json.loads(capsys.readouterr().out)
    assert round(table["amplification_A"], 2) == A
    assert abs(table["delta_eff_first_order"] - d_eff) < 0.01
    # The output says where first-order and exact parallax differ.
    assert table["delta_eff_exact"] != pytest.approx(table["delta_eff_first_order"], abs=1e-3)
    assert "first-order" in table["differences"]
    assert set(table["dperiod"]) == {"p1", "p2", "delta_alpha", "a", "Z"}


def test_design_flags_write_and_plot(tmp_path, capsys):
    device_file = tmp_path / "d.json"
    plot = tmp_path / "maps.png"
    argv = ["design", "--p1", "0.35", "--p2", "0.30", "--a", "3", "--Z", "12", "--px-per-mm", "16", "--size", "512"]
    argv += ["--E", "1.0", "--nu", "0.49", "--thickness", "3", "--alpha1-deg", "0.5", "--layout", "lines"]
    assert main([*argv, "--write", str(device_file), "--plot", str(plot)]) == 0
    out = capsys.readouterr().out
    assert "amplification A" in out and "dLambda/d" in out
    device = mj.load_device(device_file)
    assert device.layout == "lines" and abs(float(device.alpha1) - 0.5 * 3.141592653589793 / 180) < 1e-12
    assert plot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_design_sets_every_value_a_unit_has(tmp_path, capsys):
    # Duty of each grating, the cross angle and every optical value, as a unit measured
    # elsewhere would need them; the rest stays the preset's.
    device_file = tmp_path / "unit.json"
    argv = ["design", "--preset", "mid", "--duty1", "0.5", "--duty2", "0.7", "--cross-angle-deg", "88"]
    optics = {"defocus": 0.03, "psf_sigma": 1.1, "background": 0.8, "vignetting": 0.3, "glow_gain": 0.0}
    optics |= {"glow_width": 1.5, "rim_gain": 0.0, "rim_width": 0.4, "gain": 0.7, "offset": 0.02, "gamma": 1.2}
    for name, value in optics.items():
        argv += [f"--{name.replace('_', '-')}", str(value)]
    assert main([*argv, "--write", str(device_file)]) == 0
    device, nominal = mj.load_device(device_file), mj.preset("mid")
    assert float(device.duty1) == pytest.approx(0.5) and float(device.duty2) == pytest.approx(0.7)
    assert float(device.cross_angle) == pytest.approx(88 * 3.141592653589793 / 180)
    for name, value in optics.items():
        assert float(getattr(device.optics, name)) == pytest.approx(value), name
    assert float(device.p1) == float(nominal.p1) and float(device.elastomer.E) == float(nominal.elastomer.E)
    assert main(["design", "--preset", "mid", "--duty1", "1.5"]) == 2
    assert "duty1" in capsys.readouterr().err


@pytest.mark.parametrize(
    "argv, fragment, code",
    [
        # A design the flags describe that cannot be built: a usage error (2).
        (["--p1", "-0.3", "--p2", "0.3"], "p1", 2),
        (["--p1", "0.35", "--p2", "0.3", "--a", "12", "--Z", "12"], "a < Z", 2),
        (["--p1", "0.375", "--p2", "0.3", "--a", "3", "--Z", "12"], "infinite", 2),
        # A file that cannot be read: bad input (3), naming the flag.
        (["--device", "/nonexistent/device.json"], "no such file (given by --device)", 3),
    ],
)
def test_design_bad_input_is_one_clear_line(capsys, argv, fragment, code):
    assert main(["design", *argv]) == code
    err = capsys.readouterr().err
    assert fragment in err
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1
