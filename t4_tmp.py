import time, json, sys
from eofnn.interop.oopao import OopaoLoop
from eofnn.interop.study import run_study, StudyConfig
t=time.time()
kw=eval(sys.argv[1])
sim=OopaoLoop(10, 2.0, dm_gain=2.0, **kw)
r=run_study(sim, StudyConfig(**eval(sys.argv[2]) if len(sys.argv)>2 else {}), dm_gain_true=2.0)
s=r.summary()
print(kw, "ident", round(s["identified"]["dm_gain"],4), "noise", round(s["identified"]["wfs_noise_nm"],2), "replay", round(s["replay"]["predictor_median_rms_nm"],2), round(s["replay"]["integrator_median_rms_nm"],2), "int", s["integrator"]["best_gain"], round(s["integrator"]["median_rms_nm"],2), "eof", round(s["eof"]["median_rms_nm"],2), s["eof"]["alpha"], round(time.time()-t))
