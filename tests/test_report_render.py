"""report: it opens with what it ran on, renders its Markdown as HTML, rounds, folds and leaves out."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pandas as pd
from test_report_build import _results

from waveforest import config
from waveforest.report.markdown import format_value, round_floats, to_html
from waveforest.stages.report import run

SMOKE_CONFIG = Path(__file__).resolve().parents[1] / "config" / "test" / "config.yaml"


def _section(md: str, title: str) -> str:
    parts = re.split(r"^## (.+)$", md, flags=re.M)
    return dict(zip(parts[1::2], parts[2::2]))[title]


def _outside_pre(page: str) -> str:
    return re.sub(r"<pre>.*?</pre>", "", page, flags=re.S)


def test_source_block_names_the_virtual_campaign_config_and_small_counts(tmp_path):
    res, _ = _results(tmp_path)
    (res / "campaign" / "truth.json").write_text(json.dumps(
        {"seed": 11, "effects": {"understory": 1.5, "clumping": 0.0}, "active_effects": {"understory": 1.5}}))
    cfg = config.load(SMOKE_CONFIG)
    out = run(res, res / "report" / "report.html", cfg, config_path=SMOKE_CONFIG)
    md = out.markdown.read_text()
    assert re.findall(r"^## (.+)$", md, flags=re.M)[:2] == ["What this report ran on",
                                                           "Summary: the results beside the paper's"]
    src = _section(md, "What this report ran on")
    assert "virtual ALS60 campaign" in src and "seed 11, hidden effects: understory = 1.5" in src
    assert f"**Config**: `{SMOKE_CONFIG}`" in src
    assert "| seed | 2014 | 7 |" in src and "| simulate.compare_min_h_m.birch | 1.5 | 1 |" in src
    assert "**Warning: far fewer pulses than the paper's**" in src and "2010_12_1 birch 50 (paper 1,733)" in src
    summary = _section(md, "Summary: the results beside the paper's")
    first = summary.strip().split("\n\n")[0]
    assert "virtual" in first and "hidden effects understory = 1.5" in first
    # a sentence that states a setting reads it from the config (the smoke config: 1.0 m)
    assert "Birch waveform features use first echoes higher than 1 m only" in md


def test_source_block_without_hidden_effects_and_for_a_user_folder(tmp_path):
    res, cfg = _results(tmp_path)
    md = run(res, res / "report" / "report.html", cfg).markdown.read_text()
    first = _section(md, "Summary: the results beside the paper's").strip().split("\n\n")[0]
    assert "virtual" in first and "agree by construction" in first
    assert "**Config**: the built-in defaults" in md
    assert "truth.json not found" in md and "seed 2014, hidden effects: none" in md
    user = tmp_path / "my_campaign"
    user.mkdir()
    md = run(res, res / "report" / "report.html", dict(cfg, data=str(user))).markdown.read_text()
    assert f"**Data**: your campaign folder `{user}`." in md and "virtual" not in md


def test_html_renders_markdown_rounds_folds_and_leaves_out(tmp_path):
    res, cfg = _results(tmp_path)
    d = res / "diagnose"
    (d / "diagnose.md").write_text("# Diagnosis\n\n**Verdict: none.** See `model.yaml`.\n\n- one\n- two\n\n"
                                   "## Limits\n\n| effect | limit |\n|---|---|\n| understory | 4 LAI |\n")
    (d / "model.yaml").write_text("verdict: none\ngap:\n  before: 0.03806607933451647\n")
    (d / "candidates.csv").write_text("round,rank,name,value\n")  # header only
    pd.DataFrame(dict(i=range(100), x=[0.000123456] * 100)).to_csv(res / "extra" / "long.csv", index=False)
    out = run(res, res / "report" / "report.html", dict(cfg, datasets=["2010_12_1", "2012_10_1"]))
    page = out.html.read_text()
    text = _outside_pre(page)
    assert "`" not in text  # inline code rendered, not shown with backticks
    assert not re.search(r"\|\s*-{3,}\s*\|", text) and "\n|" not in text  # no raw pipe table
    assert "<h3>Diagnosis</h3>" in page and "<code>model.yaml</code>" in page and "<li>one</li>" in page
    assert "<td>understory</td><td>4 LAI</td>" in page
    assert "0.03807" in page and "0.03806607933451647" not in page
    assert '<div class="tbl">' in page and "overflow-x:auto" in page
    assert "Show the other 88 rows" in page and "<details>" in page and "0.000123" in page
    assert "Left out, no rows: candidates.csv." in page and "<caption>candidates.csv" not in page
    assert "not in this run</td>" not in page and "Left out of Table 4 in brief" in page


def test_markdown_helpers():
    assert to_html("a `x|y` **b**") == "<p>a <code>x|y</code> <strong>b</strong></p>"
    assert to_html("```yaml\na: `1`\n```") == "<pre><code>a: `1`</code></pre>"
    assert "<ol><li>a</li><li>b c</li></ol>" in to_html("1. a\n2. b\n   c")
    assert round_floats("x: 0.12345678, y: 12, z: 1.5") == "x: 0.1235, y: 12, z: 1.5"
    assert format_value(0.000123456) == "0.000123" and format_value(-12.857) == "-12.86"
