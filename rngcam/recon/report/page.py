"""The report's HTML: one self-contained file (styles, data URIs and a small script inline; no
network), players sharing one frame slider, figures and the runs' settings and notes."""

from __future__ import annotations

import html
import json
import math

SLOWDOWNS = (10, 30, 100, 300, 1000, 3000, 10000, 30000, 100000)

STYLE = """
body{font-family:system-ui,sans-serif;margin:1.2em auto;max-width:1200px;color:#222;padding:0 1em}
h1{font-size:1.4em;margin-bottom:.2em}h2{font-size:1.1em;border-bottom:1px solid #ccc;margin-top:1.6em}
.meta{color:#555;font-size:.9em}.warn{background:#fff4d6;border-left:4px solid #e0a800;padding:.3em .8em}
.players{display:flex;flex-wrap:wrap;gap:10px}.players figure{margin:0;text-align:center;width:var(--pw,256px)}
.players img{width:var(--pw,256px);image-rendering:pixelated;background:#000;display:block}
figcaption{font-size:.85em;margin-top:2px}.controls{position:sticky;top:0;background:#fff;z-index:2;
padding:.5em 0;border-bottom:1px solid #eee}#slider{width:100%}
#marks{position:relative;height:14px;margin:0 8px}.mark{position:absolute;top:0;transform:translateX(-50%);
font-size:10px;color:#b00;cursor:pointer}#time{font-variant-numeric:tabular-nums;font-weight:600}
.plot{position:relative;display:inline-block}.plot img{max-width:100%;display:block}
.cursor{position:absolute;top:0;bottom:0;width:0;border-left:2px solid rgba(220,0,0,.6);pointer-events:none}
table{border-collapse:collapse;font-size:.85em}td,th{border:1px solid #ccc;padding:2px 6px;text-align:right}
th:first-child,td:first-child{text-align:left;white-space:nowrap}pre{font-size:.8em;background:#f6f6f6;padding:.5em;overflow:auto}
"""

SCRIPT = r"""
(function () {
  const D = JSON.parse(document.getElementById('rngcam-data').textContent);
  const n = D.times_us.length;
  const slider = document.getElementById('slider');
  const timeText = document.getElementById('time');
  const playBtn = document.getElementById('play');
  const slow = document.getElementById('slow');
  const imgs = D.players.map(function (p, i) { return document.getElementById('player-' + i); });
  let frame = 0, timer = null;
  function fmt(x) { return x.toLocaleString('en-US', {minimumFractionDigits: 1, maximumFractionDigits: 1}); }
  function show(k) {
    frame = Math.max(0, Math.min(n - 1, k | 0));
    slider.value = frame;
    D.players.forEach(function (p, i) { imgs[i].src = p.frames[frame]; });
    const t = D.times_us[frame];
    const key = D.key_shown.indexOf(frame) >= 0 ? ' \u2014 GS key frame' : '';
    timeText.textContent = 't = ' + fmt(t) + ' \u00b5s (frame ' + D.frames[frame] + ' of 0\u2013' +
      (D.total - 1) + ')' + key;
    D.cursors.forEach(function (c) {
      const el = document.getElementById(c.id);
      const f = c.x0 + (t - c.t0) / (c.t1 - c.t0) * (c.x1 - c.x0);
      el.style.left = (100 * f) + '%';
    });
    document.body.setAttribute('data-frame', String(frame));
  }
  function stop() { if (timer) { clearInterval(timer); timer = null; } playBtn.textContent = 'Play'; }
  function start() {
    stop();
    const ms = Math.max(16, D.dt_us * D.stride * Number(slow.value) / 1000);
    timer = setInterval(function () { show(frame + 1 < n ? frame + 1 : 0); }, ms);
    playBtn.textContent = 'Pause';
  }
  function describe() {
    const fps = 1e6 / (D.dt_us * Number(slow.value));
    document.getElementById('rate').textContent = '= ' + (fps >= 1 ? fps.toFixed(1) : fps.toPrecision(2)) +
      ' video frames per second' + (D.stride > 1 ? ' (every ' + D.stride + 'th shown)' : '');
  }
  slider.addEventListener('input', function () { show(Number(slider.value)); });
  playBtn.addEventListener('click', function () { if (timer) { stop(); } else { start(); } });
  slow.addEventListener('change', function () { describe(); if (timer) { start(); } });
  document.querySelectorAll('.mark').forEach(function (m) {
    m.addEventListener('click', function () { stop(); show(Number(m.getAttribute('data-frame'))); });
  });
  document.addEventListener('keydown', function (e) {
    if (e.target.tagName === 'SELECT') { return; }
    if (e.key === 'ArrowRight') { stop(); show(frame + 1); }
    if (e.key === 'ArrowLeft') { stop(); show(frame - 1); }
  });
  function fromHash() {
    const m = /frame=(\d+)/.exec(location.hash);
    if (m) { show(Number(m[1])); }
  }
  window.addEventListener('hashchange', fromHash);
  describe();
  show(0);
  fromHash();
})();
"""


def esc(x) -> str:
    return html.escape(str(x))


def fmt(v, digits: int = 2) -> str:
    if v is None:
        return "–"
    if isinstance(v, float):
        if math.isnan(v):
            return "–"
        return f"{v:.{digits}f}"
    return esc(v)


def default_slowdown(dt_s: float) -> int:
    """The factor that plays about 12 video frames a second."""
    want = 1 / (12 * dt_s) if dt_s > 0 else 1000
    return min(SLOWDOWNS, key=lambda s: abs(math.log(s / want)))


def player_section(players: list[dict], times_us: list[float], key_shown: list[int], dt_s: float,
                   width_px: int) -> str:
    n = len(times_us)
    chosen = default_slowdown(dt_s)
    options = "".join(f'<option value="{s}"{" selected" if s == chosen else ""}>{s:,}x</option>'
                      for s in SLOWDOWNS)
    marks = "".join(f'<span class="mark" data-frame="{k}" title="GS key frame at {times_us[k]:,.1f} µs" '
                    f'style="left:{100 * k / max(1, n - 1):.3f}%">▲GS</span>' for k in key_shown)
    figs = "".join(f'<figure><img id="player-{i}" alt="{esc(p["name"])}"><figcaption>{esc(p["name"])}'
                   f'</figcaption></figure>' for i, p in enumerate(players))
    return (f'<section class="controls"><button id="play">Play</button> slow motion '
            f'<select id="slow">{options}</select> <span id="rate"></span> &nbsp; <span id="time"></span>'
            f'<input type="range" id="slider" min="0" max="{n - 1}" value="0" step="1" '
            f'aria-label="frame"><div id="marks">{marks}</div></section>'
            f'<div class="players" style="--pw:{width_px}px">{figs}</div>')


def plot_block(plot: dict, cursor_id: str, cursors: list[dict], alt: str) -> str:
    if not plot:
        return ""
    cursors.append({"id": cursor_id, **{k: plot[k] for k in ("x0", "x1", "t0", "t1")}})
    return (f'<div class="plot"><img src="{plot["uri"]}" alt="{esc(alt)}">'
            f'<div class="cursor" id="{cursor_id}"></div></div>')


def table(rows: list[dict], columns: list[tuple[str, str, int]]) -> str:
    """rows of values; columns: (key, heading, digits); columns nobody has are dropped."""
    cols = [c for c in columns if any(r.get(c[0]) is not None for r in rows)]
    head = "".join(f"<th>{esc(h)}</th>" for _, h, _ in cols)
    body = "".join("<tr>" + "".join(f"<td>{fmt(r.get(k), d)}</td>" for k, _, d in cols) + "</tr>" for r in rows)
    return f"<table><tr>{head}</tr>{body}</table>"


def script_json(data) -> str:
    """`data` as JSON that cannot end or alter the <script> element it sits in: `<`, `>` and `&`
    are written as \\u escapes (a label's `</script>` or `<!--<script>` would otherwise end the
    element or swallow its end tag), and so are U+2028/U+2029; JSON.parse reads them back unchanged."""
    text = json.dumps(data, separators=(",", ":"))
    for ch, escaped in (("<", "\\u003c"), (">", "\\u003e"), ("&", "\\u0026"),
                        ("\u2028", "\\u2028"), ("\u2029", "\\u2029")):
        text = text.replace(ch, escaped)
    return text


def page(title: str, meta_lines: list[str], warnings: list[str], sections: list[tuple[str, str]],
         data: dict) -> str:
    """The whole document; `data` (players, times, cursors) goes in as JSON for the script."""
    blob = script_json(data)
    warn = "".join(f'<p class="warn">{esc(w)}</p>' for w in warnings)
    meta = "".join(f'<div class="meta">{m}</div>' for m in meta_lines)
    body = "".join(f"<h2>{esc(h)}</h2>{content}" if h else content for h, content in sections)
    return (f'<!doctype html>\n<html lang="en"><head><meta charset="utf-8"><title>{esc(title)}</title>'
            f'<meta name="viewport" content="width=device-width, initial-scale=1">'
            f'<style>{STYLE}</style></head><body><h1>{esc(title)}</h1>{meta}{warn}{body}'
            f'<script type="application/json" id="rngcam-data">{blob}</script><script>{SCRIPT}</script>'
            f'</body></html>\n')
