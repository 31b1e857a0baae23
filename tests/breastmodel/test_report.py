"""The report on its own: parameters carry units, fit status and uncertainty; every position's
error map shares one colour scale."""

import re

import numpy as np
import pytest

from breastmodel.pipeline.report import common_error_limit, parameter_units, write_report

MODEL = {"materials": {"breast_left": {"name": "neo_hookean", "E": 0.9, "nu": 0.49},
                       "muscle": {"name": "gent", "E": 10.0, "nu": 0.49, "Jm": 2.0}},
         "effects": {"skin": {"E": 7.0}, "ligaments:medial": {}}}


def test_parameter_units_come_from_the_registry():
    assert parameter_units(MODEL, "materials.breast_left.E") == "kPa"
    assert parameter_units(MODEL, "materials.muscle.Jm") == "-"
    assert parameter_units(MODEL, "effects.skin.E") == "kPa"
    assert parameter_units(MODEL, "materials.breast_left.E|materials.muscle.E") == "kPa"
    assert parameter_units(MODEL, "effects.nothing.E") == "?"


def test_common_limit_spans_every_position():
    small, large = np.full(100, 0.5), np.linspace(-4.0, 4.0, 101)
    lim = common_error_limit([small, large])
    assert lim == pytest.approx(np.percentile(np.abs(np.r_[small, large]), 98))
    assert lim > common_error_limit([small])
    assert common_error_limit([np.zeros(3)]) == 1.0


def _skin(shift: float):
    v = np.array([[0, 0, 0], [10, 0, 0], [0, 0, 10], [10, 0, 10.0]]) + shift
    f = np.array([[0, 1, 2], [1, 3, 2]])
    return v, f


def test_report_shows_fit_status_units_uncertainty_and_one_scale(tmp_path):
    metrics = {"reference": "supine", "positions": {
        "prone": {"mhd_mm": 2.0, "converged": True},
        "supine": {"mhd_mm": 0.5, "converged": False, "load_reached": 0.5,
                   "error": "Newton diverged"}}}
    params = {"parameters": {"materials.breast_left.E": 0.9, "effects.skin.E": 7.0},
              "model": MODEL, "fitted": True}
    fit = {"method": "least_squares", "termination": "xtol reached", "n_simulations": 12,
           "n_failed": 1, "best": {"params": {"materials.breast_left.E": 0.9},
                                   "objective": 1.25},
           "uncertainty": {"materials.breast_left.E": 0.0421},
           "skin_offset_sensitivity": {"materials.breast_left.E": -0.027},
           "identifiability": {"not_separable": [["materials.breast_left.E", "effects.skin.E",
                                                  -0.97]], "unseen": [], "condition": 850.0}}
    config = {"fit": {"parameters": {"materials.breast_left.E": {"min": 0.1, "max": 4.0}}}}
    pictures = {"prone": (*_skin(0), np.array([-3.0, 1, 2, 3]), _skin(1)),
                "supine": (*_skin(0), np.array([0.1, 0.2, -0.1, 0.0]), _skin(0))}
    sf = {"method": "inverse_fixed_point", "converged": True, "forward_solves": 3,
          "history": [{"iteration": 1, "mean_error": 1.0, "max_error": 2.0}]}
    path = write_report(tmp_path / "report.html", metrics, params, pictures, fit, sf,
                        subject_id="s", config=config)
    html = path.read_text()
    rows = {}  # first table row per key (the fit table repeats the parameter names)
    for tr in re.findall(r"<tr>(.*?)</tr>", html):
        cells = re.findall(r"<td>(.*?)</td>", tr)
        if cells:
            rows.setdefault(cells[0], cells[1:])
    assert rows["materials.breast_left.E"] == ["0.900", "kPa", "fitted", "[0.1, 4]", "0.042"]
    assert rows["effects.skin.E"] == ["7.000", "kPa", "fixed", "-", "-"]
    assert rows["predict supine"][1].startswith("NOT converged")
    assert rows["predict supine"][2] == "Newton diverged"
    assert rows["fit"] == ["least_squares", "xtol reached", "12 simulations, 1 failed"]
    assert ("The data do not separate materials.breast_left.E and effects.skin.E "
            "(correlation -0.97)") in html
    # a segmentation bias: -0.027 kPa per mm on 0.9 kPa is -3 % per mm
    assert ("A measured skin 1 mm outside the true one (a segmentation bias) would move "
            "materials.breast_left.E by -3.0 % (-0.027 kPa)") in html
    lim = common_error_limit([p[2] for p in pictures.values()])
    assert f"&plusmn;{lim:.2f} mm" in html
