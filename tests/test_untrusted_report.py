"""The report page's embedded data cannot end its <script> element: a run's label such as
`</script><!--<script>` is data, read back unchanged, and the page's players keep working."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest
from browser import chromium, load

from rngcam.recon.report import figures, page

EVIL = "</script><!--<script>alert(1)</script>&amp;\u2028"


def _page(label: str) -> tuple[str, dict]:
    """A small report page: one player of four 16x16 frames named `label`."""
    video = np.random.default_rng(0).random((1, 4, 16, 16)).astype(np.float32)
    frames = np.arange(4)
    players = [{"name": label, "frames": figures.video_uris(video, frames, 1)}]
    data = {"players": players, "times_us": [208.0 * i for i in range(4)], "frames": list(range(4)), "total": 4,
            "dt_us": 208.0, "stride": 1, "key_shown": [0], "cursors": []}
    sections = [("", page.player_section(players, data["times_us"], [0], 208e-6, 160))]
    return page.page(f"report of {label}", [], [f"a warning about {label}"], sections, data), data


def test_the_embedded_json_holds_the_label_as_data():
    html, data = _page(EVIL)
    blob = re.search(r'<script type="application/json" id="rngcam-data">(.*?)</script>', html, re.S).group(1)
    # inside a script element only '<' can change the HTML tokenizer's state ('</script', '<!--'):
    # with none in the JSON, the element ends where we end it, whatever the label holds
    assert "<" not in blob and ">" not in blob and "&" not in blob and "\u2028" not in blob
    assert json.loads(blob) == data and json.loads(blob)["players"][0]["name"] == EVIL
    assert html.count("<script") == 2 and "<!--" not in html  # the label elsewhere is HTML-escaped
    assert page.script_json({"a": "x\u2029<"}) == '{"a":"x\\u2029\\u003c"}'


@pytest.mark.skipif(chromium() is None, reason="no chromium on this machine (make test installs Debian's)")
def test_a_hostile_label_keeps_the_players_working_in_a_browser(tmp_path):
    html, data = _page(EVIL)
    path = tmp_path / "report.html"
    path.write_text(html)
    dom, console = load(path, "#frame=2")
    assert console == [], console
    assert 'data-frame="2"' in dom  # the script ran and moved the slider
    # attribute values hold no '"' once serialised (the alt text's '>' may stay a '>')
    shown = re.search(r'<img id="player-0"(?:\s+[\w-]+="[^"]*")*?\s+src="([^"]+)"', dom).group(1)
    assert shown == data["players"][0]["frames"][2]
