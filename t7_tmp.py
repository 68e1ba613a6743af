import numpy as np
from eofnn.interop.oopao import OopaoLoop, quiet
sim=OopaoLoop(10, 2.0, dm_gain=2.0, wind_speed_mps=20.0)
sim.reset(0)
sim.tel-sim.atm
tilt=sim.project(sim.positions_m[:,0]*50)
for c in (tilt, -tilt, -tilt, 0*tilt, 0*tilt, tilt, tilt):
    with quiet():
        sim.dm.coefs = c*1e-9
        sim.ngs*sim.tel*sim.dm*sim.wfs
    r=sim.reconstructor@sim.slopes()
    print(round((r@tilt)/(tilt@tilt),3), np.std(sim.dm.OPD)*1e9, np.std(sim.tel.OPD[sim._pupil])*1e9)
