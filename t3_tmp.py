import time, json
from eofnn.interop.oopao import OopaoLoop
from eofnn.interop.study import run_study, StudyConfig
t=time.time()
sim=OopaoLoop(10, 2.0, dm_gain=2.0)
r=run_study(sim, StudyConfig(), dm_gain_true=2.0)
s=r.summary(); s.pop("config"); s.pop("simulator")
print(json.dumps(s, indent=1), time.time()-t)
