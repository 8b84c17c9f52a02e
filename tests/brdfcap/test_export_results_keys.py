"""Every key of ``results.json`` (and every quantity of ``coefficients.csv``) is documented.

A small capture runs through every ``--problem``; for each ``results.json``, every key that the
schema lists (all top-level keys and their children, deeper where the schema describes the
object) must be listed in the schema — the schema validates it — and named in the results.json
table of ``docs/results-format.md``. Objects the schema leaves open (``"type": "object"``
without ``properties``, or with ``additionalProperties``: maps keyed by data such as file names
or stage names, or model-specific parameter sets) are not descended into.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest
from brdfcap.capture.diligent import import_diligent, write_synthetic_diligent
from brdfcap.capture.simulate import simulate
from brdfcap.fit.problems import PROBLEMS

from brdfcap.pipeline import RunOptions, run_capture
from brdfcap.results_io import load_results_schema, validate_results
from brdfcap.testing import make_tiny_capture, scene_text

DOC = Path(__file__).resolve().parents[2] / "docs" / "results-format.md"

SPHERE = """
name = "phong sphere"
[geometry]
shape = "sphere"
radius = 1.0
[material]
model = "{model}"
albedo = [0.3, 0.3, 0.3]
{lobe}
[lighting]
{lighting}
[camera]
model = "pinhole"
width = 32
height = 32
fov_deg = 40.0
[views]
count = 3
distance = 4.0
elevation_deg = 30.0
[noise]
relative = 0.01
read = 0.002
seed = 1
"""
PHONG = 'ks = [0.5, 0.5, 0.5]\ns = 20.0'
MICROFACET = 'f0 = [0.5, 0.5, 0.5]\nsigma = 0.2'
ENV = 'kind = "environment"\nsh = "grace-rh2001"\nknown = true'
DIR = ('kind = "directional"\n[[lighting.lights]]\ndirection = [1.0, 0.3, 0.5]\n'
       '[[lighting.lights]]\ndirection = [-0.4, 0.8, 0.6]\n'
       '[[lighting.lights]]\ndirection = [0.2, -0.9, 0.4]')


# ---------------------------------------------------------------------------------------------
# the checks
# ---------------------------------------------------------------------------------------------

def _resolve(node: dict, root: dict, value) -> dict:
    """Follow ``$ref`` and pick the ``oneOf`` branch that fits ``value``'s JSON type."""
    while "$ref" in node:
        node = root["$defs"][node["$ref"].rsplit("/", 1)[1]]
    if "oneOf" in node:
        kind = "object" if isinstance(value, dict) else "array" if isinstance(value, list) \
            else "null" if value is None else None
        for branch in node["oneOf"]:
            t = branch.get("type")
            if t == kind or (isinstance(t, list) and kind in t):
                return _resolve(branch, root, value)
        return {}
    return node


def schema_keys(value, node: dict, root: dict, path: str = "") -> tuple[list[str], list[str]]:
    """``(listed, unlisted)`` dotted key paths of ``value`` under the schema ``node``.

    A dict is *closed* when its schema lists ``properties`` and sets no
    ``additionalProperties``: then each of its keys must be listed. List items share the list's
    path (``lighting.bands.l``).
    """
    node = _resolve(node, root, value)
    listed, unlisted = [], []
    if isinstance(value, list):
        for item in value:
            if isinstance(item, (dict, list)) and isinstance(node.get("items"), dict):
                a, b = schema_keys(item, node["items"], root, path)
                listed += a
                unlisted += b
        return sorted(set(listed)), sorted(set(unlisted))
    if not isinstance(value, dict):
        return [], []
    props = node.get("properties")
    if props is None or "additionalProperties" in node:
        return [], []  # open: keys are data or model-specific
    for k, v in value.items():
        p = f"{path}.{k}" if path else k
        if k not in props:
            unlisted.append(p)
            continue
        listed.append(p)
        a, b = schema_keys(v, props[k], root, p)
        listed += a
        unlisted += b
    return sorted(set(listed)), sorted(set(unlisted))


def doc_rows(text: str) -> list[tuple[set[str], set[str]]]:
    """``(named, mentioned)`` per row of the results.json table of results-format.md.

    ``named``: the keys of the first cell, a leading-dot shorthand (``.sh`` after
    ``lighting.lmax``) expanded; ``mentioned``: every backticked word of the row.
    """
    section = text.split("## results.json", 1)[1].split("\n## ", 1)[0]
    rows = []
    for line in section.splitlines():
        if not line.startswith("|") or line.startswith("|---"):
            continue
        cells = line.strip("|").split("|")
        named, parent = set(), ""
        for tok in re.findall(r"`([^`]+)`", cells[0]):
            if tok.startswith(".") and parent:
                tok = parent + tok
            named.add(tok)
            parent = tok.rsplit(".", 1)[0] if "." in tok else tok
        rows.append((named, set(re.findall(r"`([^`]+)`", line))))
    return rows


def undocumented(paths: list[str], rows) -> list[str]:
    """Paths that no row names, and whose leaf no row of an ancestor mentions."""
    out = []
    for p in paths:
        parts = p.split(".")
        ancestors = {".".join(parts[:i]) for i in range(1, len(parts))}
        ok = any(p in named for named, _ in rows) or any(
            (named & ancestors) and parts[-1] in mentioned for named, mentioned in rows)
        if not ok:
            out.append(p)
    return out


def check_results(results: dict, name: str) -> int:
    """Fail unless ``results`` validates and each key is in the schema and in the doc."""
    validate_results(results)
    schema = load_results_schema()
    listed, unlisted = schema_keys(results, schema, schema)
    assert not unlisted, f"{name}: keys the schema does not list: {unlisted}"
    missing = undocumented(listed, doc_rows(DOC.read_text()))
    assert not missing, f"{name}: keys docs/results-format.md does not name: {missing}"
    return len(listed)


def undocumented_quantities(csv_text: str, doc: str) -> list[str]:
    """``coefficients.csv`` quantities that its section of results-format.md does not name."""
    section = doc.split("## coefficients.csv", 1)[1].split("\n## ", 1)[0]
    section = re.sub(r"```.*?```", "", section, flags=re.S)  # the example block
    named = set(re.findall(r"`([^`]+)`", section))
    names = {ln.split(",", 1)[0] for ln in csv_text.splitlines()[1:] if ln}
    return sorted(q for q in names
                  if q not in named and re.sub(r"_p\d+$", "_p<p>", q) not in named)


def test_the_check_can_fail():
    schema = load_results_schema()
    r = {"format": "brdfcap-results/1", "lighting": None, "brdf": {"model": "m",
                                                                   "parameters": {"x": 1}},
         "fit": {"n_samples": 1, "residual_rms": 0.0, "residual_rel": 0.0, "new_key": 1},
         "undocumented_block": {"a": 1}}
    listed, unlisted = schema_keys(r, schema, schema)
    assert unlisted == ["fit.new_key", "undocumented_block"]
    doc = "## coefficients.csv\n- `quantity`: `lighting`, `rho_lpq_p<p>`\n## next"
    csv = "quantity,index\nlighting,0\nrho_lpq_p3,1\nnew_thing,\n"
    assert undocumented_quantities(csv, doc) == ["new_thing"]
    assert "brdf.parameters" in listed and "brdf.parameters.x" not in listed  # open object
    rows = doc_rows("## results.json\n| key | meaning |\n|---|---|\n"
                    "| `lighting.lmax`, `.sh` | x |\n| `fit` | `n_samples` and more |\n## next")
    assert undocumented(["lighting.sh", "fit.n_samples", "fit.residual_rms", "lighting.frame"],
                        rows) == ["fit.residual_rms", "lighting.frame"]


# ---------------------------------------------------------------------------------------------
# every problem
# ---------------------------------------------------------------------------------------------

@pytest.mark.slow
def test_every_problem_writes_only_documented_schema_keys(tmp_path):
    """One small capture per ``--problem`` and a raw capture (~8 min on 2 busy cores)."""
    d = tmp_path
    caps = {}
    for name, model, lobe, light in (("env", "phong", PHONG, ENV), ("dir", "phong", PHONG, DIR),
                                     ("mf", "microfacet", MICROFACET, ENV)):
        (d / f"{name}.toml").write_text(SPHERE.format(model=model, lobe=lobe, lighting=light))
        caps[name] = simulate(d / f"{name}.toml", d / name)
    toml = (caps["mf"] / "capture.toml").read_text()
    (caps["mf"] / "capture.toml").write_text(toml.replace(
        "[lighting]\n", "[lighting]\nsources = [[0.3, 0.2, 0.9], [-0.5, 0.4, 0.7]]\n", 1))
    tiny = make_tiny_capture(d / "tiny")
    write_synthetic_diligent(d / "diligent", size=24, n_lights=16, noise_rel=0.005)
    normal_map = import_diligent(d / "diligent", d / "nm")
    runs = {"auto": (tiny, {"lmax": 4}),
            "aldrian-smith": (tiny, {}),
            "lighting": (caps["env"], {"lmax": 3}),
            "brdf": (caps["dir"], {}),
            "both": (caps["env"], {"lmax": 2, "brdf_lmax": 2}),
            "brdf-isotropic": (caps["env"], {"brdf_lmax": 2}),
            "decomposition": (caps["mf"], {"lmax": 2}),
            "brdf-map": (normal_map, {})}
    assert set(runs) == set(PROBLEMS)
    for problem, (cap, opts) in runs.items():
        out = d / f"o_{problem}"
        run_capture(cap, out, RunOptions(problem=problem, **opts))
        results = json.loads((out / "results.json").read_text())
        assert results["fit"]["problem"] == problem
        assert check_results(results, problem) > 40
        missing = undocumented_quantities((out / "coefficients.csv").read_text(),
                                          DOC.read_text())
        assert not missing, f"{problem}: coefficients.csv quantities not documented: {missing}"
    # a raw capture adds its linearisation chain to every image record
    (d / "raw.toml").write_text(scene_text(
        extra='[camera_raw]\neffects = ["colour_matrix", "white_balance", "cfa", '
              '"black_white_level", "noise"]\n', width=32, views=2))
    run_capture(simulate(d / "raw.toml", d / "raw"), d / "o_raw", RunOptions())
    results = json.loads((d / "o_raw" / "results.json").read_text())
    assert "white_balance" in results["images"][0]
    check_results(results, "raw capture")
