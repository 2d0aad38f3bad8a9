"""3-D views as one self-contained HTML file: opens offline in any browser, no tacest, no
network, no JavaScript library (a small canvas renderer is inlined, ~150 lines).

What it shows: the estimated shape (filled, shaded), the true shape (green edges), the
ground grid, the fingertips (spheres seen as discs) with the path they have travelled,
and at each contact the contact point and the measured normal (red).  A slider and a
play button step through the frames; drag to orbit, the wheel zooms; ``FILE.html#frame=N``
opens at frame N.

The data are a JSON document in ``<script type="application/json" id="tacest-data">``:
``{"title", "dim", "frames": [{"k", "t", "est": pose|null, "truth": pose|null,
"fingers": [[x, y, z], ...], "contacts": [[px, py, pz, nx, ny, nz], ...]}],
"est_shape": {"vertices", "faces", "edges"}|null, "true_shape": ...|null, "finger_radius",
"finger_path": [[[x, y, z], ...] per finger]}`` (m, poses ``[x, y, z, qw, qx, qy, qz]``),
so a script can read a view back (tests/test_view.py does).
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np

from tacest.errors import TacestError
from tacest.io.outputs import atomic_file
from tacest.view.scene import Scene, frame_indices

log = logging.getLogger(__name__)

#: m, drawn normal length
NORMAL_LENGTH = 0.03
#: rad, two hull triangles meeting at more than this angle share a drawn edge (1e-6:
#: coplanar triangles of one face meet at 0 up to rounding)
FEATURE_ANGLE = 1e-6


def _shape(vertices):
    from tacest.geometry.polytope import convex_hull_mesh

    mesh = convex_hull_mesh(vertices)
    # the polytope's edges: hull triangle edges between faces that are not coplanar
    edges = mesh.face_adjacency_edges[mesh.face_adjacency_angles > FEATURE_ANGLE]
    return {"vertices": np.round(np.asarray(mesh.vertices), 6).tolist(), "faces": np.asarray(mesh.faces).tolist(),
            "edges": np.asarray(edges).tolist()}


def scene_json(sc: Scene, fps: float = 20.0, max_frames: int = 600) -> dict:
    """The JSON document of ``sc`` (module docstring)."""
    if sc.dim != 3:
        raise TacestError("the HTML view is for 3-D runs and estimates (2-D: write a .gif or .mp4)")
    dt = float(np.median(np.diff(sc.time))) if sc.n_samples > 1 else 0.01
    idx = frame_indices(sc.n_samples, dt, fps, max_frames)
    r6 = lambda a: np.round(np.asarray(a, float), 6).tolist()  # noqa: E731  (µm is plenty)
    frames = []
    for k in idx:
        fr = {"k": int(k), "t": round(float(sc.time[k]), 6),
              "est": r6(sc.est_pose[k]) if sc.est_pose is not None else None,
              "truth": r6(sc.true_pose[k]) if sc.true_pose is not None else None,
              "fingers": [], "contacts": []}
        if sc.finger_position is not None:
            fr["fingers"] = r6(sc.finger_position[k])
            for f in np.flatnonzero(sc.contact[k]):
                n = sc.normal[k, f]
                p = sc.finger_position[k, f] - sc.finger_radius[f] * n
                fr["contacts"].append(r6(np.concatenate([p, n])))
        frames.append(fr)
    return {
        "title": sc.title, "dim": 3, "time_known": bool(sc.time_known), "frames": frames,
        "est_shape": _shape(sc.est_vertices) if sc.est_pose is not None else None,
        "true_shape": _shape(sc.true_vertices) if sc.true_pose is not None else None,
        "finger_radius": r6(sc.finger_radius) if sc.finger_radius is not None else [],
        "finger_path": (r6(np.transpose(sc.finger_position[idx], (1, 0, 2))) if sc.finger_position is not None
                        else []),
        "normal_length": NORMAL_LENGTH,
    }


_PAGE = r"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><title>__TITLE__</title>
<style>
body{font-family:sans-serif;margin:0;background:#fafafa;color:#222}
#bar{padding:6px 10px;display:flex;gap:10px;align-items:center;flex-wrap:wrap}
#c{display:block;background:#fff;border-top:1px solid #ddd;border-bottom:1px solid #ddd;cursor:grab}
#slider{flex:1;min-width:200px}.key span{display:inline-block;width:12px;height:12px;margin:0 3px 0 10px;vertical-align:middle}
</style></head><body>
<div id="bar"><button id="play">play</button><input id="slider" type="range" min="0" value="0">
<span id="when"></span></div>
<canvas id="c" width="900" height="600"></canvas>
<div id="bar" class="key"><b id="title"></b>
<span style="background:#d9792b"></span>estimated shape<span style="background:#2a7f2a"></span>true shape
<span style="background:#2f5fb3"></span>finger and path<span style="background:#c0392b"></span>contact and normal
&nbsp; drag: orbit, wheel: zoom</div>
<script type="application/json" id="tacest-data">__DATA__</script>
<script>
"use strict";
const D=JSON.parse(document.getElementById("tacest-data").textContent);
const cv=document.getElementById("c"),g=cv.getContext("2d"),sl=document.getElementById("slider");
document.getElementById("title").textContent=D.title;
sl.max=D.frames.length-1;
function rot(q,v){const [w,x,y,z]=q;const tx=2*(y*v[2]-z*v[1]),ty=2*(z*v[0]-x*v[2]),tz=2*(x*v[1]-y*v[0]);
 return [v[0]+w*tx+(y*tz-z*ty),v[1]+w*ty+(z*tx-x*tz),v[2]+w*tz+(x*ty-y*tx)];}
function place(p,v){const r=rot(p.slice(3),v);return [r[0]+p[0],r[1]+p[1],r[2]+p[2]];}
// the scene's centre and size, for the camera
let lo=[1e9,1e9,1e9],hi=[-1e9,-1e9,-1e9];
function grow(v){for(let i=0;i<3;i++){lo[i]=Math.min(lo[i],v[i]);hi[i]=Math.max(hi[i],v[i]);}}
for(const f of D.frames){for(const [s,p] of [[D.est_shape,f.est],[D.true_shape,f.truth]])
 if(s&&p)for(const v of s.vertices)grow(place(p,v));for(const q of f.fingers)grow(q);}
grow([lo[0],lo[1],0]);
const ctr=[(lo[0]+hi[0])/2,(lo[1]+hi[1])/2,(lo[2]+hi[2])/2];
const size=Math.max(hi[0]-lo[0],hi[1]-lo[1],hi[2]-lo[2],0.05);
let az=-0.9,el=0.45,dist=2.0*size;
function view(v){const x=v[0]-ctr[0],y=v[1]-ctr[1],z=v[2]-ctr[2];
 const ca=Math.cos(az),sa=Math.sin(az),ce=Math.cos(el),se=Math.sin(el);
 const xr=ca*x-sa*y,yr=sa*x+ca*y;              // about z
 const right=xr,depth=yr*ce+z*se,up=-yr*se+z*ce; // tilt
 return [right,up,dist-depth];}
const dist0=dist,px=0.5*Math.min(cv.width,cv.height)/size; // pixels per m at the start distance
function proj(v){const c=view(v),f=px*dist0/Math.max(c[2],1e-6);
 return [cv.width/2+f*c[0],cv.height/2-f*c[1],c[2],f];}
const light=[0.4,-0.7,0.9];
function shade(n){const l=Math.hypot(...light);return 0.35+0.65*Math.max(0,(n[0]*light[0]+n[1]*light[1]+n[2]*light[2])/l);}
function tris(shape,pose){const W=shape.vertices.map(v=>place(pose,v));
 return shape.faces.map(f=>{const a=W[f[0]],b=W[f[1]],c=W[f[2]];
  const u=[b[0]-a[0],b[1]-a[1],b[2]-a[2]],w=[c[0]-a[0],c[1]-a[1],c[2]-a[2]];
  const n=[u[1]*w[2]-u[2]*w[1],u[2]*w[0]-u[0]*w[2],u[0]*w[1]-u[1]*w[0]],nl=Math.hypot(...n)||1;
  return {p:[a,b,c].map(proj),n:n.map(x=>x/nl)};});}
function line(a,b,col,wd){const p=proj(a),q=proj(b);g.strokeStyle=col;g.lineWidth=wd;g.beginPath();
 g.moveTo(p[0],p[1]);g.lineTo(q[0],q[1]);g.stroke();}
function draw(i){const f=D.frames[i];g.clearRect(0,0,cv.width,cv.height);
 // ground grid, 1 cm lines over the scene
 const step=Math.pow(10,Math.floor(Math.log10(size/2))),gx0=Math.floor((lo[0]-size/2)/step)*step,gy0=Math.floor((lo[1]-size/2)/step)*step;
 for(let x=gx0;x<=hi[0]+size/2;x+=step)line([x,gy0,0],[x,hi[1]+size/2,0],"#e4e4e4",1);
 for(let y=gy0;y<=hi[1]+size/2;y+=step)line([gx0,y,0],[hi[0]+size/2,y,0],"#e4e4e4",1);
 // finger paths so far
 D.finger_path.forEach(path=>{g.strokeStyle="rgba(47,95,179,0.6)";g.lineWidth=1.5;g.beginPath();
  for(let j=0;j<=i;j++){const p=proj(path[j]);j?g.lineTo(p[0],p[1]):g.moveTo(p[0],p[1]);}g.stroke();});
 const items=[];
 if(D.est_shape&&f.est)for(const t of tris(D.est_shape,f.est)){
  const s=shade(t.n);items.push({z:(t.p[0][2]+t.p[1][2]+t.p[2][2])/3,fn:()=>{g.fillStyle=`rgba(${217*s|0},${121*s|0},${43*s|0},0.55)`;
  g.beginPath();g.moveTo(t.p[0][0],t.p[0][1]);g.lineTo(t.p[1][0],t.p[1][1]);g.lineTo(t.p[2][0],t.p[2][1]);g.closePath();g.fill();}});}
 f.fingers.forEach((q,k)=>{const p=proj(q);items.push({z:p[2],fn:()=>{g.fillStyle="rgba(47,95,179,0.75)";g.beginPath();
  g.arc(p[0],p[1],Math.max(2,D.finger_radius[k]*p[3]),0,2*Math.PI);g.fill();}});});
 items.sort((a,b)=>b.z-a.z).forEach(it=>it.fn());
 if(D.true_shape&&f.truth){const W=D.true_shape.vertices.map(v=>place(f.truth,v));
  for(const e of D.true_shape.edges)line(W[e[0]],W[e[1]],"#2a7f2a",2);}
 for(const c of f.contacts){const p=c.slice(0,3),e=[p[0]+c[3]*D.normal_length,p[1]+c[4]*D.normal_length,p[2]+c[5]*D.normal_length];
  line(p,e,"#c0392b",2.5);const q=proj(p);g.fillStyle="#c0392b";g.beginPath();g.arc(q[0],q[1],4,0,2*Math.PI);g.fill();}
 document.getElementById("when").textContent=(D.time_known?`t = ${f.t.toFixed(2)} s`:`sample ${f.k}`)+`  (frame ${i+1}/${D.frames.length}, ${f.contacts.length} contact(s))`;}
let cur=0,timer=null;
function show(i){cur=i;sl.value=i;draw(i);}
sl.oninput=()=>show(+sl.value);
document.getElementById("play").onclick=function(){if(timer){clearInterval(timer);timer=null;this.textContent="play";return;}
 this.textContent="pause";timer=setInterval(()=>show((cur+1)%D.frames.length),50);};
let drag=null;cv.onmousedown=e=>{drag=[e.clientX,e.clientY];};window.onmouseup=()=>{drag=null;};
window.onmousemove=e=>{if(!drag)return;az-=(e.clientX-drag[0])*0.01;el=Math.max(-1.5,Math.min(1.5,el+(e.clientY-drag[1])*0.01));
 drag=[e.clientX,e.clientY];draw(cur);};
cv.onwheel=e=>{e.preventDefault();dist*=Math.exp(e.deltaY*0.001);draw(cur);};
const h=/frame=(\d+)/.exec(location.hash);show(h?Math.min(+h[1],D.frames.length-1):0);
</script></body></html>
"""


def write_html_3d(sc: Scene, path, fps: float = 20.0, max_frames: int = 600) -> int:
    """Write the HTML view of ``sc`` (3-D) to ``path``; returns the number of frames."""
    path = Path(path)
    if path.suffix.lower() not in (".html", ".htm"):
        raise TacestError(f"{path}: a 3-D view is an .html file")
    doc = scene_json(sc, fps=fps, max_frames=max_frames)
    data = json.dumps(doc, separators=(",", ":"), allow_nan=False).replace("</", "<\\/")
    title = sc.title.replace("&", "&amp;").replace("<", "&lt;").replace(">", "&gt;")
    with atomic_file(path) as tmp:
        tmp.write_text(_PAGE.replace("__TITLE__", title).replace("__DATA__", data))
    log.info("wrote %s: %d frames", path, len(doc["frames"]))
    return len(doc["frames"])
