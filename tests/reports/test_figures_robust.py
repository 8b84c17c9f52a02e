"""reports.figures: user text is not mathtext, and a failing figure never costs the results
(issue #17 row 10).
"""

from __future__ import annotations

import base64

import numpy as np
from brdfcap.reports import figures as F
from brdfcap.reports.brdf_figures import brdf_sh_figure

BAD_NAME = r"view $\frac{1$ a.exr"


def _png_bytes(uri: str) -> bytes:
    assert uri.startswith("data:image/png;base64,")
    return base64.b64decode(uri.split(",", 1)[1])


def test_file_name_with_broken_mathtext_is_drawn_as_text():
    img = np.random.default_rng(0).random((8, 8, 3)).astype(np.float32)
    m = np.ones((8, 8), bool)
    before = len(F.FIGURE_FAILURES)
    uri = F.fig_to_data_uri(F.thumbnails_figure([img], [m], [BAD_NAME]))
    uri2 = F.fig_to_data_uri(F.residual_figure([img], [img], [m], [BAD_NAME]))
    assert len(F.FIGURE_FAILURES) == before  # drawn, not replaced by a placeholder
    assert _png_bytes(uri)[:4] == b"\x89PNG" and _png_bytes(uri2)[:4] == b"\x89PNG"
    assert F.plain_text(BAD_NAME) == r"view \$\frac{1\$ a.exr"


def test_failure_at_draw_time_gives_a_placeholder_and_a_record(caplog):
    fig = F.plt.figure()
    fig.text(0.1, 0.5, BAD_NAME)  # unescaped: mathtext raises only when drawn
    with caplog.at_level("WARNING", logger="brdfcap.reports"):
        uri = F.fig_to_data_uri(fig)
    assert _png_bytes(uri)[:4] == b"\x89PNG"
    assert "could not be drawn" in F.FIGURE_FAILURES[-1]
    assert "\n" not in F.FIGURE_FAILURES[-1]
    assert any("could not be drawn" in r.message for r in caplog.records)


def test_failure_inside_a_builder_gives_a_placeholder():
    class Broken:  # an SH record missing every field the builder reads
        lmax = 2

    before = len(F.FIGURE_FAILURES)
    fig = brdf_sh_figure(Broken())
    uri = F.fig_to_data_uri(fig)
    assert _png_bytes(uri)[:4] == b"\x89PNG"
    assert len(F.FIGURE_FAILURES) == before + 1
    assert "brdf_sh_figure" in F.FIGURE_FAILURES[-1]
