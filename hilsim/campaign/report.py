"""``report.html``: one self-contained page (no CDN, no external file) with the campaign's table.

A filter box (any text), a status filter and a filter per column (``>0.1``,
``<5``, ``=pass`` or text) narrow the rows; each mission run links to the
stack's plots and summary and to the bridge's and the stack's logs; each render
frame links to its PNGs and .npz.
"""

from __future__ import annotations

import html
import json
import math
from pathlib import Path
from typing import Any

from hilsim.campaign.results import flatten
from hilsim.campaign.spec import Campaign

_STYLE = """
body{font:13px system-ui,sans-serif;margin:1em}table{border-collapse:collapse}
th,td{border:1px solid #ccc;padding:2px 5px;text-align:left;vertical-align:top;white-space:nowrap}
th{background:#eee;position:sticky;top:0}td.fail,td.error,td.timeout{background:#fdd}td.pass,td.done{background:#dfd}
input.col{width:6em}.small{color:#666}td.wrap{white-space:normal;max-width:28em}
"""
_SCRIPT = """
function num(s){var v=parseFloat(s);return isNaN(v)?null:v}
function keep(cell,f){f=f.trim();if(!f)return true;var t=cell.textContent;
 var m=f.match(/^(<=|>=|<|>|=)(.*)$/);if(m){var a=num(t),b=num(m[2]);
  if(m[1]=='=')return t.trim()==m[2].trim();if(a===null||b===null)return false;
  return m[1]=='<'?a<b:m[1]=='>'?a>b:m[1]=='<='?a<=b:a>=b}
 return t.toLowerCase().indexOf(f.toLowerCase())>=0}
function apply(){var q=document.getElementById('q').value.toLowerCase(),
 st=document.getElementById('st').value,cols=document.querySelectorAll('input.col'),n=0;
 document.querySelectorAll('#runs tbody tr').forEach(function(tr){
  var ok=(!q||tr.textContent.toLowerCase().indexOf(q)>=0)&&(!st||tr.dataset.status==st);
  cols.forEach(function(inp){if(ok)ok=keep(tr.children[+inp.dataset.i],inp.value)});
  tr.style.display=ok?'':'none';if(ok)n++});
 document.getElementById('n').textContent=n}
document.addEventListener('input',apply);document.addEventListener('change',apply);
"""


def _cell(v: Any) -> str:
    if v is None:
        return ""
    if isinstance(v, float):
        return "" if not math.isfinite(v) else f"{v:.6g}"
    if isinstance(v, bool):
        return "true" if v else "false"
    return str(v)


def _links(out: Path, row: dict[str, Any], kind: str) -> str:
    items: list[tuple[str, str]] = []
    if kind == "mission":
        run = f"runs/{row.get('run_dir') or row.get('case')}"
        folder = out / run
        for p in sorted((folder / "stack").glob("*.png")):
            items.append((p.stem, f"{run}/stack/{p.name}"))
        for name, rel in (("summary", "stack/summary.json"), ("stack log", "stack.log"), ("bridge log", "bridge.log"),
                          ("truth", "truth.csv"), ("bridge summary", "bridge_summary.json")):
            if (folder / rel).is_file():
                items.append((name, f"{run}/{rel}"))
    else:
        for k, v in sorted((row.get("files") or {}).items()):
            items.append((k, str(v)))
    return " ".join(f'<a href="{html.escape(h)}">{html.escape(n)}</a>' for n, h in items)


def _columns(flat: list[dict[str, Any]], kind: str) -> list[str]:
    seen: dict[str, None] = {}
    for r in flat:
        for k in r:
            seen.setdefault(k, None)
    if kind == "mission":
        head = ["case", "status", "failed", "failure"]
        params = sorted(k for k in seen if k.startswith("param."))
        rest = ["seed", "exit_code", "wall_s"] + sorted(k for k in seen if k.startswith("truth."))
        rest += [k for k in ("bridge.late_ticks", "bridge.contacts.count", "summary.success", "summary.failure",
                             "summary.duration_s") if k in seen]
        return [k for k in head + params + rest if k in seen]
    head = ["case", "frame", "seed", "x_m", "y_m", "z_m", "roll_deg", "pitch_deg", "yaw_deg", "rays_hit"]
    return [k for k in head if k in seen] + sorted(k for k in seen if k.startswith(("hits.", "cells."))) + \
        [k for k in ("shadow_cells", "render_ms") if k in seen]


def write_report(c: Campaign, rows: list[dict[str, Any]], out: Path) -> Path:
    flat = sorted(((flatten(r), r) for r in rows), key=lambda fr: (fr[0].get("index", 0), fr[0].get("frame", 0)))
    cols = _columns([f for f, _ in flat], c.kind)
    statuses = sorted({str(f.get("status")) for f, _ in flat})
    counts = {s: sum(1 for f, _ in flat if f.get("status") == s) for s in statuses}
    head = "".join(f"<th>{html.escape(k)}</th>" for k in cols) + "<th>links</th>"
    filt = "".join(f'<th><input class="col" data-i="{i}" placeholder="filter"></th>' for i in range(len(cols))) + "<th></th>"
    body = []
    for f, r in flat:
        st = html.escape(str(f.get("status", "")))
        tds = []
        for k in cols:
            cls = f' class="{st}"' if k == "status" else ' class="wrap"' if k == "failure" else ""
            tds.append(f"<td{cls}>{html.escape(_cell(f.get(k)))}</td>")
        body.append(f'<tr data-status="{st}">{"".join(tds)}<td>{_links(out, r, c.kind)}</td></tr>')
    opts = "".join(f'<option value="{html.escape(s)}">{html.escape(s)} ({counts[s]})</option>' for s in statuses)
    crit = "".join(f"<li><code>{html.escape(k.name)}</code>: <code>{html.escape(k.text)}</code></li>" for k in c.criteria)
    table = "results.parquet" if c.kind == "mission" else "index.parquet"
    page = f"""<!doctype html><html><head><meta charset="utf-8"><title>campaign {html.escape(c.name)}</title>
<style>{_STYLE}</style></head><body>
<h1>campaign {html.escape(c.name)}</h1>
<p class="small">{html.escape(str(c.path))} &middot; scenario {html.escape(str(c.scenario))} &middot; {c.kind}
&middot; {len(flat)} rows: {html.escape(json.dumps(counts))} &middot; full table in <code>{table}</code></p>
{"<p>pass criteria:</p><ul>" + crit + "</ul>" if crit else ""}
<p>filter <input id="q" placeholder="any text"> status <select id="st"><option value="">all</option>{opts}</select>
&middot; <span id="n">{len(flat)}</span> shown &middot; column filters take text, =x, &lt;x, &gt;x</p>
<table id="runs"><thead><tr>{head}</tr><tr>{filt}</tr></thead><tbody>
{chr(10).join(body)}
</tbody></table><script>{_SCRIPT}</script></body></html>
"""
    path = out / "report.html"
    path.write_text(page)
    return path
