"""index.html: one self-contained page of a result folder, for any browser, offline.

The page holds its data (base64 float32/uint32 arrays in a JSON block) and a small WebGL
viewer; it makes no network request (its Content-Security-Policy is ``default-src 'none'``
and the one inline script it allows by its SHA-256 hash, so no other script can run) and needs no server: open the file. It shows

- the deployed surface (deployed.vtu, mm), coloured by any of the fields the folder has:
  mean curvature (1/mm), region, side, distance to the target (% of the bounding-box
  diagonal, a design's --verify);
- the target as a translucent ghost where there is one (a design's flat.vtu point data
  ``target``: the same frame as the registered deployed.vtu);
- the flat pattern beside it (pattern.svg redrawn from its polylines by geometry.cad, so
  nothing but polygons is embedded), and the run's summary line.

Drag to orbit, wheel to zoom, double-click to reset. ``write_view`` is `selfshape view DIR`;
`selfshape simulate` and `design` write the same page (:func:`folder_page`) once their other
files are written, before their summary. pyvista's own export_html needs trame (a server-side
framework) and is not used.
"""
from __future__ import annotations

import base64
import hashlib
import html
import json
import os
import re

import numpy as np

from shellfem.errors import SelfshapeError
from shellfem.outfiles import check_finite_arrays

#: The result files a folder needs for a page (any one of them; deployed.vtu or flat.vtu draws).
VIEW_INPUTS = ("deployed.vtu", "flat.vtu")
#: The target ghost is decimated to at most this many triangles (a design refines its target to
#: up to 600k faces; a ghost needs its shape, not its resolution, and the page stays small)
GHOST_TRIANGLES = 40_000


def coarsened(points, triangles, max_triangles: int = GHOST_TRIANGLES):
    """(points, triangles) with at most about ``max_triangles`` triangles: VTK's decimation
    (pyvista) when there are more, else unchanged."""
    tri = np.asarray(triangles)
    if len(tri) <= max_triangles:
        return np.asarray(points, float), tri
    import pyvista as pv
    d = pv.PolyData.from_regular_faces(np.asarray(points, float), tri).decimate(1.0 - max_triangles / len(tri))
    return np.asarray(d.points, float), d.faces.reshape(-1, 4)[:, 1:]


def _b64(a, dtype) -> str:
    return base64.b64encode(np.ascontiguousarray(a, dtype=dtype).tobytes()).decode("ascii")


def _mesh_json(points, triangles, fields=None) -> dict:
    """{points, triangles, fields: {name: {on: "cell"|"point", kind, values}}} for the page."""
    pts = np.asarray(points, float)
    check_finite_arrays("index.html", {"positions": pts})
    out = {"n": int(len(pts)), "m": int(len(triangles)), "points": _b64(pts, "<f4"),
           "triangles": _b64(triangles, "<u4"), "fields": {}}
    for name, (on, kind, values) in (fields or {}).items():
        v = np.asarray(values, float)
        if not np.isfinite(v).all():
            continue
        out["fields"][name] = {"on": on, "kind": kind, "values": _b64(v, "<f4")}
    return out


def deployed_fields(cell_data: dict, point_data: dict) -> dict:
    """The colourings of a deployed.vtu's data: {label: (on, kind, values)}; kind "diverging"
    (signed, around 0), "sequential", "category" (integer ids) or "side" (+1 front, -1 back,
    0 bare, 2 both)."""
    f = {}
    if "mean_curvature_per_mm" in cell_data:
        f["mean curvature (1/mm)"] = ("cell", "diverging", cell_data["mean_curvature_per_mm"])
    if "distance_pct_bbox" in point_data:
        f["distance to target (% of diagonal)"] = ("point", "sequential", point_data["distance_pct_bbox"])
    if "region" in cell_data:
        f["region"] = ("cell", "category", cell_data["region"])
    if "side" in cell_data:
        f["side (front red, back blue)"] = ("cell", "side", cell_data["side"])
    if "thickness_mm" in cell_data:
        f["plastic thickness (mm)"] = ("cell", "sequential", cell_data["thickness_mm"])
    return f


def page_html(deployed=None, target=None, shapes=None, title: str = "selfshape", summary: str = "") -> str:
    """The page (see the module doc). deployed: (points (n, 3) mm, triangles, fields as
    :func:`deployed_fields`) or None; target: (points, triangles) or None; shapes: the flat
    pattern's geometry.cad.Shape list or None; summary: one line shown under the title."""
    from geometry.cad import svg_text
    data = {"title": title,
            "deployed": _mesh_json(*deployed) if deployed is not None else None,
            "target": _mesh_json(*target) if target is not None else None}
    svg = svg_text(shapes, inline=True) if shapes else ""
    blob = json.dumps(data, allow_nan=False).replace("</", "<\\/")
    fill = {"TITLE": html.escape(title), "SUMMARY": html.escape(summary), "CSP": CSP,
            "SVG": svg or '<p class="none">no flat pattern in this folder</p>', "DATA": blob, "SCRIPT": _SCRIPT}
    # one pass, so that no filled-in text is itself searched for placeholders
    return re.sub(r"@(TITLE|SUMMARY|CSP|SVG|DATA|SCRIPT)@", lambda m: fill[m.group(1)], _PAGE)


def _read_vtu(path):
    from shellfem.infiles import read_meshio
    m = read_meshio(path, "VTU file", path)
    blocks = [c.data for c in m.cells if c.type == "triangle"]
    if not blocks:
        raise SelfshapeError(f"{path}: holds no triangles to draw")
    tri = np.vstack(blocks)
    cells = {k: np.concatenate([np.asarray(b) for b, c in zip(v, m.cells) if c.type == "triangle"])
             for k, v in m.cell_data.items()}
    return m.points, tri, cells, {k: np.asarray(v) for k, v in m.point_data.items()}


def _summary_line(folder: str) -> str:
    for name in ("summary.json", "report.json"):
        p = os.path.join(folder, name)
        if os.path.isfile(p):
            try:
                with open(p, encoding="utf-8") as f:
                    s = json.load(f)
            except (OSError, ValueError):
                return ""
            return summary_text(s)
    return ""


def summary_text(s: dict) -> str:
    """One line of a summary.json (simulate) or report.json (design) for the page."""
    if "newton_iterations" in s:
        return (f"{'converged' if s.get('converged') else 'NOT converged'} in {s['newton_iterations']} Newton "
                f"iterations, {s.get('n_vertices', '?')} vertices, bbox "
                + " x ".join(f"{v:.1f}" for v in s.get("bbox_mm", [])) + " mm")
    parts = [f"{s.get('n_ribbons', '?')} ribbons, stretch {s.get('stretch', '?')}"]
    dev = s.get("deviation_pct_bbox")
    if dev:
        parts.append(f"deployed -> target {dev[0]:.2f} / {dev[1]:.2f} % of the diagonal (mean / max)")
    return ", ".join(parts)


def folder_page(folder, summary: dict | None = None, *, target: bool = True) -> str:
    """The page of a simulate or design output folder (SelfshapeError naming the folder if it
    holds none of VIEW_INPUTS). ``summary``: the run's summary.json/report.json dict (default:
    read from the folder). ``target``: draw a design's flat.vtu target (False for a simulation,
    whose deployed.vtu is not registered to a target)."""
    from geometry.cad import read_svg
    folder = os.fspath(folder)
    if not os.path.isdir(folder):
        raise SelfshapeError(f"{folder}: is not a folder of results (selfshape simulate or design output)")
    have = [n for n in VIEW_INPUTS if os.path.isfile(os.path.join(folder, n)) and (target or n != "flat.vtu")]
    if not have:
        raise SelfshapeError(f"{folder}: no results to view (no {' or '.join(VIEW_INPUTS)}; run selfshape "
                             f"simulate or design -o {folder} first)")
    deployed = ghost = shapes = None
    if "deployed.vtu" in have:
        pts, tri, cells, points = _read_vtu(os.path.join(folder, "deployed.vtu"))
        deployed = (pts, tri, deployed_fields(cells, points))
    if "flat.vtu" in have:
        pts, tri, cells, points = _read_vtu(os.path.join(folder, "flat.vtu"))
        if "target" in points:
            ghost = coarsened(points["target"], tri)
            if deployed is None:        # a design without --verify: the target is the surface
                deployed, ghost = (points["target"], tri, {}), None
    svg = os.path.join(folder, "pattern.svg")
    if os.path.isfile(svg):
        shapes = read_svg(svg)[0]
    title = os.path.basename(os.path.abspath(folder))
    line = summary_text(summary) if summary is not None else _summary_line(folder)
    return page_html(deployed, ghost, shapes, title=title, summary=line)


def write_view(folder) -> str:
    """`selfshape view DIR`: write DIR/index.html (atomically) from the folder's results; returns its path."""
    from shellfem.outfiles import write_text_file
    text = folder_page(folder)
    return write_text_file(os.path.join(os.fspath(folder), "index.html"), text)


_PAGE = """<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8">
<meta http-equiv="Content-Security-Policy" content="@CSP@">
<meta name="viewport" content="width=device-width, initial-scale=1">
<title>@TITLE@</title>
<style>
html,body{margin:0;height:100%;font:14px system-ui,sans-serif;background:#f4f4f2;color:#222}
body{display:flex;flex-direction:column}
header{padding:6px 12px;border-bottom:1px solid #ccc;background:#fff}
header h1{font-size:16px;margin:0 12px 0 0;display:inline}
#main{display:flex;flex:1;min-height:0}
#left{flex:3;position:relative;min-width:0}
#gl{width:100%;height:100%;display:block;cursor:grab}
#right{flex:2;border-left:1px solid #ccc;background:#fff;overflow:auto;padding:8px;min-width:0}
#right svg{width:100%;height:calc(100% - 24px)}
#right #fabric polygon{fill:#eeeeea}
#right g[id^="front"] polygon{fill:#d62728;fill-opacity:.55}
#right g[id^="back"] polygon{fill:#1f77b4;fill-opacity:.55}
#ui{position:absolute;left:8px;top:8px;background:rgba(255,255,255,.85);padding:6px;border-radius:4px}
#legend{position:absolute;left:8px;bottom:8px;background:rgba(255,255,255,.85);padding:4px 6px;border-radius:4px}
#bar{width:200px;height:10px}
.none{color:#888}
</style></head><body>
<header><h1>@TITLE@</h1><span>@SUMMARY@</span></header>
<div id="main"><div id="left"><canvas id="gl"></canvas>
<div id="ui"><label>colour <select id="field"></select></label>
<label id="ghostl"><input type="checkbox" id="ghost" checked> target (green ghost)</label></div>
<div id="legend"><canvas id="bar" width="200" height="10"></canvas><div id="range"></div></div></div>
<div id="right"><b>flat pattern</b> (printed state, mm)<br>@SVG@</div></div>
<script type="application/json" id="data">@DATA@</script>
<script>@SCRIPT@</script>
</body></html>
"""

_SCRIPT = r"""
"use strict";
const D = JSON.parse(document.getElementById("data").textContent);
function dec(s, T){const b=atob(s),u=new Uint8Array(b.length);for(let i=0;i<b.length;i++)u[i]=b.charCodeAt(i);return new T(u.buffer);}
function mesh(M){if(!M)return null;const o={n:M.n,m:M.m,p:dec(M.points,Float32Array),t:dec(M.triangles,Uint32Array),f:{}};
 for(const k in M.fields){const F=M.fields[k];o.f[k]={on:F.on,kind:F.kind,v:dec(F.values,Float32Array)};}return o;}
const dep=mesh(D.deployed), tgt=mesh(D.target);
const canvas=document.getElementById("gl");
const gl=canvas.getContext("webgl",{antialias:true,preserveDrawingBuffer:true});
const rangeEl=document.getElementById("range");
if(!gl){rangeEl.textContent="this browser has no WebGL: the 3D view cannot be drawn";}
// colour maps
const DIV=[[0.23,0.30,0.75],[0.87,0.87,0.87],[0.71,0.02,0.15]];
const SEQ=[[0.27,0.00,0.33],[0.23,0.32,0.55],[0.13,0.57,0.55],[0.37,0.79,0.38],[0.99,0.91,0.14]];
const CAT=[[0.75,0.75,0.72],[0.84,0.15,0.16],[0.12,0.47,0.71],[1.0,0.5,0.05],[0.17,0.63,0.17],[0.58,0.40,0.74],[0.55,0.34,0.29],[0.89,0.47,0.76],[0.5,0.5,0.5],[0.74,0.74,0.13],[0.09,0.75,0.81]];
function ramp(st,x){x=Math.min(1,Math.max(0,x))*(st.length-1);const i=Math.min(st.length-2,Math.floor(x)),f=x-i;return [0,1,2].map(c=>st[i][c]*(1-f)+st[i+1][c]*f);}
function sideCol(s){return s>1.5?[0.55,0.25,0.6]:s>0.5?[0.84,0.15,0.16]:s<-0.5?[0.12,0.47,0.71]:[0.75,0.75,0.72];}
function quant(v,q){const a=Array.from(v).sort((x,y)=>x-y);return a.length?a[Math.min(a.length-1,Math.floor(q*(a.length-1)))]:0;}
function colours(M,name){const c=new Float32Array(M.m*9);const F=M.f[name];let lo=0,hi=1,st=null,label="";
 if(F&&(F.kind==="diverging")){hi=Math.max(quant(F.v.map(Math.abs),0.98),1e-12);lo=-hi;st=DIV;}
 else if(F&&F.kind==="sequential"){lo=quant(F.v,0.0);hi=Math.max(quant(F.v,0.98),lo+1e-12);st=SEQ;}
 for(let f=0;f<M.m;f++)for(let k=0;k<3;k++){const vi=M.t[3*f+k];let col=[0.8,0.8,0.78];
  if(F){const x=F.on==="cell"?F.v[f]:F.v[vi];
   if(F.kind==="category")col=CAT[((x|0)%CAT.length+CAT.length)%CAT.length];else if(F.kind==="side")col=sideCol(x);else col=ramp(st,(x-lo)/(hi-lo));}
  c.set(col,9*f+3*k);}
 const bar=document.getElementById("bar").getContext("2d");bar.clearRect(0,0,200,10);
 if(st){for(let i=0;i<200;i++){const q=ramp(st,i/199);bar.fillStyle="rgb("+q.map(x=>Math.round(255*x)).join(",")+")";bar.fillRect(i,0,1,10);}
  label=lo.toPrecision(3)+" \u2026 "+hi.toPrecision(3);}
 document.getElementById("bar").style.display=st?"block":"none";
 rangeEl.textContent=F?(st?name+": "+label:name):"";return c;}
function geometry(M){const P=new Float32Array(M.m*9),N=new Float32Array(M.m*9),vn=new Float32Array(M.n*3);
 for(let f=0;f<M.m;f++){const a=M.t[3*f],b=M.t[3*f+1],c=M.t[3*f+2];
  const ux=M.p[3*b]-M.p[3*a],uy=M.p[3*b+1]-M.p[3*a+1],uz=M.p[3*b+2]-M.p[3*a+2];
  const wx=M.p[3*c]-M.p[3*a],wy=M.p[3*c+1]-M.p[3*a+1],wz=M.p[3*c+2]-M.p[3*a+2];
  const nx=uy*wz-uz*wy,ny=uz*wx-ux*wz,nz=ux*wy-uy*wx;
  for(const v of [a,b,c]){vn[3*v]+=nx;vn[3*v+1]+=ny;vn[3*v+2]+=nz;}}
 for(let f=0;f<M.m;f++)for(let k=0;k<3;k++){const v=M.t[3*f+k];
  const l=Math.hypot(vn[3*v],vn[3*v+1],vn[3*v+2])||1;
  for(let j=0;j<3;j++){P[9*f+3*k+j]=M.p[3*v+j];N[9*f+3*k+j]=vn[3*v+j]/l;}}
 return {P:P,N:N};}
const VS="attribute vec3 p;attribute vec3 n;attribute vec3 c;uniform mat4 mv;uniform mat4 pr;varying vec3 vn;varying vec3 vc;"+
 "void main(){vn=mat3(mv)*n;vc=c;gl_Position=pr*mv*vec4(p,1.0);}";
const FS="precision mediump float;varying vec3 vn;varying vec3 vc;uniform float alpha;"+
 "void main(){float d=abs(normalize(vn).z);gl_FragColor=vec4(vc*(0.35+0.65*d),alpha);}";
let prog,bufs={};
function sh(t,s){const o=gl.createShader(t);gl.shaderSource(o,s);gl.compileShader(o);return o;}
function buf(a){const b=gl.createBuffer();gl.bindBuffer(gl.ARRAY_BUFFER,b);gl.bufferData(gl.ARRAY_BUFFER,a,gl.STATIC_DRAW);return b;}
const first=dep||tgt;let ctr=[0,0,0],rad=1,up=2;
if(first){const lo=[1e30,1e30,1e30],hi=[-1e30,-1e30,-1e30];for(const M of [dep,tgt])if(M)for(let i=0;i<M.n;i++)for(let j=0;j<3;j++){lo[j]=Math.min(lo[j],M.p[3*i+j]);hi[j]=Math.max(hi[j],M.p[3*i+j]);}
 ctr=[0,1,2].map(j=>(lo[j]+hi[j])/2);
 const ext=[0,1,2].map(j=>hi[j]-lo[j]);up=ext.indexOf(Math.min(...ext));rad=Math.max(0.5*Math.hypot(hi[0]-lo[0],hi[1]-lo[1],hi[2]-lo[2]),1e-9);}
let yaw=-0.6,pitch=0.6,dist=2.7;
function reset(){yaw=-0.6;pitch=0.6;dist=2.7;}
function matmul(a,b){const o=new Float32Array(16);for(let i=0;i<4;i++)for(let j=0;j<4;j++){let s=0;for(let k=0;k<4;k++)s+=a[k*4+j]*b[i*4+k];o[i*4+j]=s;}return o;}
function draw(){if(!gl||!first)return;const r=window.devicePixelRatio||1,w=Math.round(canvas.clientWidth*r),h=Math.round(canvas.clientHeight*r);if(canvas.width!==w||canvas.height!==h){canvas.width=w;canvas.height=h;}
 gl.viewport(0,0,w,h);gl.clearColor(0.96,0.96,0.95,1);gl.clear(gl.COLOR_BUFFER_BIT|gl.DEPTH_BUFFER_BIT);gl.enable(gl.DEPTH_TEST);
 const f=1/Math.tan(0.35),asp=w/Math.max(h,1),zn=0.05*dist*rad,zf=10*dist*rad;
 const pr=new Float32Array([f/asp,0,0,0, 0,f,0,0, 0,0,(zf+zn)/(zn-zf),-1, 0,0,2*zf*zn/(zn-zf),0]);
 const cy=Math.cos(yaw),sy=Math.sin(yaw),cp=Math.cos(pitch),sp=Math.sin(pitch);
 // the shape's thinnest axis is "up" (a cyclic permutation P takes it to z), then rotate about it
 // by yaw, tilt by pitch and move back
 const Rz=new Float32Array([cy,sy,0,0, -sy,cy,0,0, 0,0,1,0, 0,0,0,1]);
 const Rx=new Float32Array([1,0,0,0, 0,sp,-cp,0, 0,cp,sp,0, 0,0,0,1]);
 const T=new Float32Array([1,0,0,0, 0,1,0,0, 0,0,1,0, -ctr[0],-ctr[1],-ctr[2],1]);
 const B=new Float32Array([1,0,0,0, 0,1,0,0, 0,0,1,0, 0,0,-dist*rad,1]);
 const P=[new Float32Array([0,0,1,0, 1,0,0,0, 0,1,0,0, 0,0,0,1]),new Float32Array([0,1,0,0, 0,0,1,0, 1,0,0,0, 0,0,0,1]),
  new Float32Array([1,0,0,0, 0,1,0,0, 0,0,1,0, 0,0,0,1])][up];
 const mv=matmul(B,matmul(Rx,matmul(Rz,matmul(P,T))));
 gl.useProgram(prog);gl.uniformMatrix4fv(gl.getUniformLocation(prog,"pr"),false,pr);gl.uniformMatrix4fv(gl.getUniformLocation(prog,"mv"),false,mv);
 const pass=(b,a)=>{for(const [nm,bb] of [["p",b.P],["n",b.N],["c",b.C]]){const l=gl.getAttribLocation(prog,nm);gl.bindBuffer(gl.ARRAY_BUFFER,bb);gl.enableVertexAttribArray(l);gl.vertexAttribPointer(l,3,gl.FLOAT,false,0,0);}
  gl.uniform1f(gl.getUniformLocation(prog,"alpha"),a);gl.drawArrays(gl.TRIANGLES,0,b.count);};
 if(bufs.dep)pass(bufs.dep,1.0);
 if(bufs.tgt&&(!dep||document.getElementById("ghost").checked)){gl.enable(gl.BLEND);gl.blendFunc(gl.SRC_ALPHA,gl.ONE_MINUS_SRC_ALPHA);gl.depthMask(false);
  pass(bufs.tgt,dep?0.4:1.0);gl.depthMask(true);gl.disable(gl.BLEND);}}
function upload(M,name){const g=geometry(M);return {P:buf(g.P),N:buf(g.N),C:buf(colours(M,name)),count:3*M.m};}
const sel=document.getElementById("field");
if(dep){for(const k of Object.keys(dep.f).concat(["plain"])){const o=document.createElement("option");o.textContent=k;sel.appendChild(o);}}
else sel.parentNode.style.display="none";
if(!tgt||!dep)document.getElementById("ghostl").style.display="none";
if(gl&&first){prog=gl.createProgram();gl.attachShader(prog,sh(gl.VERTEX_SHADER,VS));gl.attachShader(prog,sh(gl.FRAGMENT_SHADER,FS));gl.linkProgram(prog);
 if(dep)bufs.dep=upload(dep,sel.value);
 if(tgt){const g=geometry(tgt),C=new Float32Array(tgt.m*9);for(let i=0;i<tgt.m*3;i++)C.set([0.05,0.45,0.25],3*i);bufs.tgt={P:buf(g.P),N:buf(g.N),C:buf(C),count:3*tgt.m};}
 sel.onchange=()=>{gl.bindBuffer(gl.ARRAY_BUFFER,bufs.dep.C);gl.bufferData(gl.ARRAY_BUFFER,colours(dep,sel.value),gl.STATIC_DRAW);draw();};
 document.getElementById("ghost").onchange=draw;
 let drag=null;canvas.style.touchAction="none";
 canvas.onpointerdown=e=>{drag=[e.clientX,e.clientY];canvas.setPointerCapture(e.pointerId);};canvas.onpointerup=canvas.onpointercancel=()=>{drag=null;};
 canvas.onpointermove=e=>{if(!drag)return;yaw+=0.01*(e.clientX-drag[0]);pitch=Math.max(-1.55,Math.min(1.55,pitch+0.01*(e.clientY-drag[1])));drag=[e.clientX,e.clientY];draw();};
 canvas.onwheel=e=>{e.preventDefault();dist*=Math.exp(0.001*e.deltaY);draw();};canvas.ondblclick=()=>{reset();draw();};
 window.onresize=draw;draw();document.title=document.title+" \u00b7 drawn";}
"""

#: The page's Content-Security-Policy: nothing may load; only the viewer script (by its hash) runs
CSP = ("default-src 'none'; script-src 'sha256-" + base64.b64encode(hashlib.sha256(_SCRIPT.encode()).digest()).decode()
       + "'; style-src 'unsafe-inline'")
