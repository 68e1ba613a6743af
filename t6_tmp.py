import time
from eofnn.interop.oopao import OopaoLoop, measure_sensor_gain
t=time.time()
sim=OopaoLoop(10, 2.0, dm_gain=2.0, wind_speed_mps=20.0)
print(measure_sensor_gain(sim, 0.25, 1500, 0), time.time()-t)
