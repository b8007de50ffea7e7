"""report.html: every cell that comes from the user's files is HTML-escaped."""

from implantplan.analyses.report import Markup, render

EVIL = "<script>alert('x')</script>&"


def plan(name=EVIL, site=EVIL):
    check = {"name": "line1 (rod) clearance", "site": site, "value": 0.002, "limit": 0.0,
             "unit": "m", "margin": 0.002, "pass": True}
    return {
        "case": {"name": name, "source": f"/cases/{name}.yaml", "seed": 0},
        "passed": True,
        "checks": [check, {**check, "site": None, "pass": False}],
        "fpsm": {"slices": 3, "control_points": 5, "z_range": [0.0, 0.1], "method": "exact",
                 "coverage_mean": 0.9, "dense_penetration_rate": None, "dense_max_depth": 0.0,
                 "mouth_opening_deg": 0.0},
        "sites": [{
            "name": site,
            "placement": {"d_T": 0.05, "theta_T": 0.1, "f_safe_line1": 0.01,
                          "f_safe_line2": 0.01, "d_safe_min_line1": 0.002,
                          "d_safe_min_line2": 0.003, "F_safe": -0.1, "iterations": 20,
                          "valid": True, "grid_check": None},
            "ik": {"branch": 0, "q": [0.0] * 6, "q_pre": [0.1] * 6},
            "capability": {"map_reachable": True, "voxel_index": 1.0,
                           "neighbourhood_index": 0.9, "ik_branches_within_limits": 8},
            "simulation": None,
        }],
        "base": {"xyz_in_oral": [0.5, -0.4, 0.0],
                 "indices_worst_over_sites": {"dexterity": 0.3, "error_range": 1e-3,
                                              "joint_variation": 0.2},
                 "percentiles": {"dexterity": 80.0, "error_range": 90.0,
                                 "joint_variation": 85.0},
                 "pareto": [], "generations": 3, "evaluations": 100},
    }


def test_user_text_is_escaped_everywhere():
    page = render(plan(), {"sites": {EVIL: ["figures/a b.png"]}, "simulation": {EVIL: []}})
    assert "<script>" not in page
    assert page.count("&lt;script&gt;alert(&#x27;x&#x27;)&lt;/script&gt;&amp;") >= 5
    # the report's own markup stays markup: one pass and one FAIL badge in the checks table
    assert "<span class='pass'>pass</span>" in page
    assert "<span class='fail'>FAIL</span>" in page


def test_a_cell_starting_with_a_bracket_is_not_trusted():
    # the old rule let any cell that started with '<' through unescaped
    page = render(plan(site="<b>46</b>"), {})
    assert "<b>46</b>" not in page and "&lt;b&gt;46&lt;/b&gt;" in page


def test_markup_cells_pass_through_and_plain_cells_do_not():
    from implantplan.analyses.report import table_cell

    assert table_cell(Markup("<i>x</i>")) == "<i>x</i>"
    assert table_cell("<i>x</i>") == "&lt;i&gt;x&lt;/i&gt;"
    assert table_cell(3) == "3"
    page = render(plan(name="plain"), {})
    assert page.startswith("<!DOCTYPE html>") and "Implant plan: plain" in page
