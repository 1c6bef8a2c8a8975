import time
from racing_env.track import get_track, circuit
from racing_env.config import RaceConfig
from racing_env.env import RacingParallelEnv
from racing_env.car_classes import get_car
from experiments.tournament import race_lineup
t0 = time.time()
track = circuit("Monza", 0.1)
race = RaceConfig(num_agents=3, track=track, vehicles=get_car("f1tenth"), race_distance=60.0, max_steps=400)
try:
    rec, _ = race_lineup(race, ["raceline"] * 3, seed=0, replay=False, cars=["f1tenth"] * 3)
    for c in rec["cars"]:
        print({k: c[k] for k in ("start_place", "place", "finish_time", "collision_steps", "time_off_track", "faults", "distance")})
    print(rec["incidents"])
except Exception as e:
    print("ERR", type(e).__name__, e)
print(time.time() - t0)
