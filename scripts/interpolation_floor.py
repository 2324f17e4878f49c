#!/usr/bin/env python3
"""The `slow` variant's scoring floor: a trajectory thinned to scans 0.7 s apart and interpolated the way the
relations metric interpolates (nearest pose within 0.1 s, else linear between poses at most 1.5 s apart),
scored against the relations. Usage: interpolation_floor.py TRAJECTORY.tum RELATIONS
"""
import math,sys,bisect
def load_tum(p):
    out=[]
    for l in open(p):
        f=l.split()
        t=float(f[0]);x=float(f[1]);y=float(f[2]);qz=float(f[6]);qw=float(f[7])
        out.append((t,x,y,2*math.atan2(qz,qw)))
    return out
def compose(a,b):
    x,y,t=a;c,s=math.cos(t),math.sin(t)
    return (x+c*b[0]-s*b[1],y+s*b[0]+c*b[1],t+b[2])
def inv(a):
    x,y,t=a;c,s=math.cos(t),math.sin(t)
    return (-(c*x+s*y),-(-s*x+c*y),-t)
def wrap(a): return math.atan2(math.sin(a),math.cos(a))
def pose_at(tr,ts,t):
    i=bisect.bisect_left(ts,t)
    best=None
    for k in (i-1,i):
        if 0<=k<len(tr) and abs(ts[k]-t)<=0.1 and (best is None or abs(ts[k]-t)<abs(ts[best]-t)): best=k
    if best is not None: return tr[best][1:]
    if i==0 or i>=len(tr): return None
    a,b=tr[i-1],tr[i]
    if b[0]-a[0]>1.5: return None
    f=(t-a[0])/(b[0]-a[0]); st=compose(inv(a[1:]),b[1:])
    return compose(a[1:],(st[0]*f,st[1]*f,wrap(st[2])*f))
tr=load_tum(sys.argv[1]); period=0.7
thin=[];last=None
for p in tr:
    if last is None or p[0]-last>=period: thin.append(p); last=p[0]
ts=[p[0] for p in thin]
errs=[]
for l in open(sys.argv[2]):
    f=l.split()
    if len(f)<8: continue
    t1,t2=float(f[0]),float(f[1]);ref=(float(f[2]),float(f[3]),float(f[7]))
    a,b=pose_at(thin,ts,t1),pose_at(thin,ts,t2)
    if a is None or b is None: continue
    e=compose(inv(a),b)
    errs.append((math.hypot(e[0]-ref[0],e[1]-ref[1]),abs(wrap(e[2]-ref[2]))*180/math.pi))
n=len(errs)
print(f"{sys.argv[1]}: n={n} trans {sum(e[0] for e in errs)/n:.4f} rot {sum(e[1] for e in errs)/n:.3f} torn {sum(1 for e in errs if e[0]>0.3 or e[1]>3)}")
