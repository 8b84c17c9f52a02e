"""The report draws every registered BRDF model (issue 13): slices from the registry's point
evaluation, a Dirac lobe (mirror) as an arrow at the mirror angle with its weight.
"""

import math

import numpy as np
import pytest
import torch
from brdfcap.fit.brdf import brdf_model_names, make_brdf
from brdfcap.fit.brdf_models import brdf_value
from brdfcap.reports import figures as F

PARAMS = {"lambertian": {"kd": [0.5, 0.4, 0.3]},
          "phong": {"kd": [0.3, 0.3, 0.3], "ks": [0.4, 0.3, 0.2], "s": 20.0},
          "beckmann": {"kd": [0.2, 0.2, 0.2], "f0": [0.9, 0.6, 0.3], "sigma": 0.2},
          "ggx": {"kd": [0.2, 0.2, 0.2], "f0": [0.04] * 3, "sigma": 0.3,
                  "fresnel": "dielectric", "eta": 1.5},
          "mirror": {"kd": [0.1, 0.1, 0.1], "ks": [0.8, 0.7, 0.6]}}


@pytest.mark.parametrize("name", brdf_model_names(aliases=False))
def test_every_registered_model_is_drawn_from_its_point_evaluation(name):
    params = PARAMS.get(name, {})
    results_brdf = make_brdf(name, **params).to_json()   # what results.json["brdf"] holds
    spec = F.brdf_spec_from_results(results_brdf)
    assert spec is not None and spec.model == name
    failures = len(F.FIGURE_FAILURES)
    fig = F.brdf_plots_figure(spec, theta_o_deg=(0.0, 40.0))
    assert len(F.FIGURE_FAILURES) == failures, F.FIGURE_FAILURES[-1:]
    ax1 = fig.axes[0]
    lines = ax1.get_lines()
    assert len(lines) == 2 * 3                     # two θo × R, G, B
    # the drawn slice is the registry's point evaluation at those angles (θo = 40°, green)
    x, y = lines[4].get_data()
    ti = np.radians(x)
    t = math.radians(40.0)
    wi = torch.as_tensor(np.stack([-np.sin(ti), np.zeros_like(ti), np.cos(ti)], -1))
    wo = torch.tensor([[math.sin(t), 0.0, math.cos(t)]], dtype=torch.float64).expand_as(wi)
    n = torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64).expand_as(wi)
    np.testing.assert_allclose(y, brdf_value(spec, n, wi, wo)[:, 1].numpy(), rtol=1e-12)
    arrows = [c for c in ax1.get_children() if (c.get_gid() or "").startswith("delta-")]
    if make_brdf(name).delta:
        # a Dirac lobe has no finite value: an arrow at θi = θo for each θo, and a spoke of
        # length k_s (green) in the polar plot
        assert sorted(a.get_gid() for a in arrows) == ["delta-0", "delta-40"]
        spokes = [ln for ln in fig.axes[1].get_lines() if ln.get_gid() == "delta-40"]
        assert len(spokes) == 1
        np.testing.assert_allclose(spokes[0].get_ydata(), [0.0, params["ks"][1]])
        np.testing.assert_allclose(spokes[0].get_xdata(), [t, t])
    else:
        assert not arrows
        assert float(np.nanmax(y)) > 0
    F.plt.close(fig)


def test_brdf_figures_for_every_model_give_a_plot():
    for name in brdf_model_names(aliases=False):
        out = F.brdf_figures(make_brdf(name, **PARAMS.get(name, {})).to_json())
        assert set(out) == {"brdf_plots"} and out["brdf_plots"].startswith("data:image/png")
