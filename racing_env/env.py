"""RacingParallelEnv: a PettingZoo ParallelEnv of N cars racing on a track.

Physics runs in one jitted function per step for all cars (``_physics_step``); the
bookkeeping around it (rewards, finishing order, the PettingZoo dictionaries) is small
NumPy work.

Actions are normalised jerks in ``[-1, 1]^2``, scaled by each car's jerk limits
``(jx_max, jy_max)``. Finite actions outside the box are clipped to it (the only silent
correction); NaN/inf, wrong shapes and unknown or missing agents are refused with an
error and leave the environment unchanged.
"""

from __future__ import annotations

import warnings
from typing import Any, Mapping

import gymnasium
import jax
import jax.numpy as jnp
import numpy as np
from pettingzoo import ParallelEnv

from racing_env.config import RaceConfig
from racing_env.dynamics import STATE_DIM, S
from racing_env.game import RaceGame
from racing_env.observation import observation_size, observe
from racing_env.physics import enforce_limits, footprint_overlap, off_track, saturate_jerk
from racing_env.scenarios import make_scenario
from racing_env.track import get_track


@jax.jit
def _physics_step(game: RaceGame, x, active, u, finish_s, preview):
    """Advance the active cars, enforce their limits, detect incidents and observe."""
    u = saturate_jerk(x, u, game.vehicles, game.dt)
    x_next = enforce_limits(game.step(x, u), game.vehicles)
    x_next = jnp.where(active[:, None], x_next, x)
    contact = footprint_overlap(x_next, game.vehicles, game.track)
    contact = contact & active[:, None] & active[None, :]
    outside = off_track(x_next, game.track) & active
    obs = observe(x_next, active, game.track, finish_s, preview).astype(jnp.float32)
    return x_next, contact, outside, obs


@jax.jit
def _observe(game: RaceGame, x, active, finish_s, preview):
    return observe(x, active, game.track, finish_s, preview).astype(jnp.float32)


def agent_name(index: int) -> str:
    return f"car_{index}"


class RacingParallelEnv(ParallelEnv):
    """N point-mass cars racing in a Frenet frame (PettingZoo Parallel API).

    ``state()`` returns the joint state ``(N, 6)`` (full information for planners);
    ``game`` is the ``RaceGame`` the planners should use. ``infos[agent]`` holds ``s``,
    ``lap``, ``position`` (1 = leading), ``collided``, ``contact_with``, ``off_track``,
    ``finished``, ``finish_time`` [s] (None until finished), ``out`` (retired by an incident rule) and the
    ``reward_terms``.
    """

    metadata = {"render_modes": ["rgb_array", "human"], "name": "racing_v0", "render_fps": 10}

    def __init__(self, config: RaceConfig | None = None, **kwargs: Any) -> None:
        if config is None:
            config = RaceConfig(**kwargs)
        elif kwargs:
            raise ValueError("pass either a RaceConfig or keyword arguments, not both")
        self.config = config
        self.render_mode = config.render_mode
        self.track = get_track(config.track)
        num = config.num_agents
        self.possible_agents = [agent_name(i) for i in range(num)]
        self.agents: list[str] = []
        self._index = {a: i for i, a in enumerate(self.possible_agents)}
        scenario = make_scenario(config.scenario, self.track, num, config.vehicles, seed=0)
        self.game = RaceGame.create(
            self.track, scenario.vehicles, config.weights, dt=config.dt, horizon=config.horizon
        )
        if config.race_distance is not None:
            self.finish_s = float(config.race_distance)
        elif self.track.closed:
            self.finish_s = float(config.laps * self.track.length)
        else:
            self.finish_s = float(self.track.length - 20.0)
        self._preview = jnp.asarray(config.preview_distances, dtype=jnp.float64)
        # device copies, so a step does not re-transfer the track and parameters each call
        self._game_on_device = jax.device_put(self.game)
        self._finish_on_device = jnp.asarray(self.finish_s, dtype=jnp.float64)
        self._jerk_max = np.asarray(self.game.vehicles.jerk_max, dtype=np.float64)  # (N, 2)
        obs_dim = observation_size(num, len(config.preview_distances))
        # every finite float32 vector (physical units, no natural bounds): finite limits,
        # because Gymnasium's check_env warns about infinite Box bounds
        big = np.finfo(np.float32).max
        self._obs_space = gymnasium.spaces.Box(-big, big, (obs_dim,), np.float32)
        self._act_space = gymnasium.spaces.Box(-1.0, 1.0, (2,), np.float32)
        self.state_space = gymnasium.spaces.Box(-np.inf, np.inf, (num, STATE_DIM), np.float64)
        self._rng = np.random.default_rng()
        self._x = np.zeros((num, STATE_DIM))
        self._renderer = None

    # --- spaces ---------------------------------------------------------------------------
    def observation_space(self, agent: str) -> gymnasium.spaces.Box:
        self._check_agent(agent)
        return self._obs_space

    def action_space(self, agent: str) -> gymnasium.spaces.Box:
        self._check_agent(agent)
        return self._act_space

    def _check_agent(self, agent: str) -> None:
        if agent not in self._index:
            raise KeyError(f"unknown agent {agent!r}; agents are {self.possible_agents}")

    @property
    def num_cars(self) -> int:
        return len(self.possible_agents)

    # --- episode --------------------------------------------------------------------------
    def reset(self, seed: int | None = None, options: Mapping[str, Any] | None = None):
        """Start a race. ``options`` may hold ``x0`` (a joint start state ``(N, 6)``)."""
        if seed is not None:
            self._rng = np.random.default_rng(seed)
        scenario_seed = int(self._rng.integers(2**31 - 1))
        options = dict(options or {})
        if "x0" in options:
            x0 = np.array(options.pop("x0"), dtype=np.float64)
            if x0.shape != (self.num_cars, STATE_DIM) or not np.all(np.isfinite(x0)):
                raise ValueError(
                    f"options['x0'] must be a finite array of shape {(self.num_cars, STATE_DIM)}, "
                    f"got shape {x0.shape}"
                )
        else:
            x0 = make_scenario(self.config.scenario, self.track, self.num_cars, None, scenario_seed).x0
        if options:
            # PettingZoo's parallel_api_test resets with options={"options": 1}: unknown keys
            # are ignored with a warning rather than refused.
            warnings.warn(f"ignoring unknown reset options {sorted(options)}; allowed: ['x0']", stacklevel=2)
        self._x = x0
        self._active = np.ones(self.num_cars, dtype=bool)
        self._finished = np.zeros(self.num_cars, dtype=bool)
        self._out = np.zeros(self.num_cars, dtype=bool)
        self._finish_time = np.full(self.num_cars, np.nan)
        self._place = np.zeros(self.num_cars, dtype=int)
        self._steps = 0
        self.agents = list(self.possible_agents)
        obs = np.array(_observe(self._game_on_device, x0, self._active, self._finish_on_device, self._preview))
        positions = self._positions()
        no_incident = np.zeros(self.num_cars, dtype=bool)
        no_contact = np.zeros((self.num_cars, self.num_cars), dtype=bool)
        per_car = self._infos(positions, no_incident, no_contact, no_incident, {})
        infos = {a: per_car[i] for i, a in enumerate(self.agents)}
        observations = {a: obs[self._index[a]] for a in self.agents}
        if self.render_mode == "human":
            self.render()
        return observations, infos

    def _actions_to_jerk(self, actions: Mapping[str, Any]) -> np.ndarray:
        if not self.agents:
            raise RuntimeError("the race is over (or was never started): call reset() first")
        unknown = [a for a in actions if a not in self._index]
        if unknown:
            raise KeyError(f"unknown agent(s) {unknown}; agents are {self.possible_agents}")
        retired = [a for a in actions if a not in self.agents]
        if retired:
            raise KeyError(f"agent(s) {retired} are no longer racing; live agents: {self.agents}")
        missing = [a for a in self.agents if a not in actions]
        if missing:
            raise KeyError(f"missing action(s) for {missing}; every live agent must act")
        jerk = np.zeros((self.num_cars, 2))
        for agent, action in actions.items():
            a = np.asarray(action, dtype=np.float64)
            if a.shape != (2,):
                raise ValueError(f"action of {agent} must have shape (2,) (normalised [jx, jy]), got {a.shape}")
            jerk[self._index[agent]] = a
        # One finiteness check and one clip for all cars: per-car NumPy calls were a
        # noticeable part of a step's Python time.
        if not np.isfinite(jerk).all():
            bad = next(a for a in actions if not np.isfinite(jerk[self._index[a]]).all())
            raise ValueError(f"action of {bad} must be finite, got {jerk[self._index[bad]].tolist()}")
        return np.clip(jerk, -1.0, 1.0) * self._jerk_max

    def step(self, actions: Mapping[str, Any]):
        """Apply normalised jerk actions of all live agents for one time step."""
        jerk = self._actions_to_jerk(actions)  # validates before anything changes
        cfg, num = self.config, self.num_cars
        x_prev = self._x
        out = _physics_step(
            self._game_on_device, x_prev, self._active, jerk, self._finish_on_device, self._preview
        )
        # np.asarray waits for each result; jax.device_get cost about 60 us more per step.
        x, contact, outside, obs = (np.asarray(a) for a in out)
        self._x = x
        obs = obs.copy()  # writable, as users may normalise observations in place
        self._steps += 1
        acting = self._active.copy()
        collided = contact.any(axis=1)

        # finishing: interpolate the crossing time inside the step, then rank
        crossed = acting & (self._x[:, S] >= self.finish_s)
        if crossed.any():
            frac = (self.finish_s - x_prev[:, S]) / np.maximum(self._x[:, S] - x_prev[:, S], 1e-9)
            t_cross = (self._steps - 1 + np.clip(frac, 0.0, 1.0)) * cfg.dt
            already = int(self._finished.sum())
            for rank, i in enumerate(sorted(np.flatnonzero(crossed), key=lambda j: t_cross[j])):
                self._finish_time[i] = t_cross[i]
                self._place[i] = already + rank + 1
            self._finished |= crossed

        retire_collision = cfg.on_collision in ("terminate", "both")
        retire_off = cfg.on_off_track in ("terminate", "both")
        newly_out = acting & ~crossed & ((collided & retire_collision) | (outside & retire_off))
        self._out |= newly_out
        self._active = acting & ~self._finished & ~self._out

        positions = self._positions()
        rw = cfg.reward
        terms = {
            "progress": rw.progress * (self._x[:, S] - x_prev[:, S]),
            "position": rw.position * self._position_score(positions),
            "collision": (rw.collision if cfg.on_collision in ("penalty", "both") else 0.0) * collided,
            "off_track": (rw.off_track if cfg.on_off_track in ("penalty", "both") else 0.0) * outside,
            "finish": rw.finish * crossed * (num - self._place) / max(num - 1, 1),
        }
        reward = sum(terms.values())
        truncate = self._steps >= cfg.max_steps
        live = list(self.agents)
        per_car = self._infos(positions, collided, contact, outside, terms)
        reward, active = np.asarray(reward, dtype=np.float64).tolist(), self._active.tolist()
        observations, rewards, terminations, truncations, infos = {}, {}, {}, {}, {}
        for agent in live:
            i = self._index[agent]
            observations[agent] = obs[i]
            rewards[agent] = reward[i]
            terminations[agent] = not active[i]
            truncations[agent] = truncate and active[i]
            infos[agent] = per_car[i]
        self.agents = [a for a in live if not (terminations[a] or truncations[a])]
        if self.render_mode == "human":
            self.render()
        return observations, rewards, terminations, truncations, infos

    # --- bookkeeping ----------------------------------------------------------------------
    def _positions(self) -> np.ndarray:
        """Race positions (1 = leading): finished cars by place, the rest by arc length."""
        key = np.where(self._finished, -1e12 + self._place, -self._x[:, S])
        order = np.argsort(key, kind="stable")
        positions = np.empty(self.num_cars, dtype=int)
        positions[order] = np.arange(1, self.num_cars + 1)
        return positions

    def _position_score(self, positions: np.ndarray) -> np.ndarray:
        num = self.num_cars
        behind, ahead = num - positions, positions - 1
        return (behind - ahead) / max(num - 1, 1)

    def _infos(self, positions, collided, contact, outside, terms) -> list[dict[str, Any]]:
        """Every car's info dict. Arrays become Python lists once per step: element-wise
        indexing of NumPy arrays took more time than the physics step's own Python side."""
        s = self._x[:, S].tolist()
        laps = (
            np.maximum(np.floor(self._x[:, S] / self.track.length), 0).astype(int).tolist()
            if self.track.closed
            else [0] * self.num_cars
        )
        positions, collided, outside = positions.tolist(), collided.tolist(), outside.tolist()
        finished, out, finish_time = self._finished.tolist(), self._out.tolist(), self._finish_time.tolist()
        contact = contact.tolist()
        terms = {k: np.asarray(v, dtype=np.float64).tolist() for k, v in terms.items()}
        return [
            {
                "s": s[i],
                "lap": laps[i],
                "position": positions[i],
                "collided": collided[i],
                "contact_with": [name for name, touching in zip(self.possible_agents, contact[i]) if touching],
                "off_track": outside[i],
                "finished": finished[i],
                # None until finished (not NaN: NaN != NaN breaks equality checks and JSON)
                "finish_time": finish_time[i] if finished[i] else None,
                "out": out[i],
                "reward_terms": {k: v[i] for k, v in terms.items()},
            }
            for i in range(self.num_cars)
        ]

    def state(self) -> np.ndarray:
        """Joint state ``(N, 6)`` = ``[s, V, n, chi, ax, ay]`` per car (a copy)."""
        return self._x.copy()

    @property
    def active(self) -> np.ndarray:
        """Which cars are still racing, ``(N,)`` bool (a copy)."""
        return self._active.copy()

    # --- rendering ------------------------------------------------------------------------
    def render(self) -> np.ndarray | None:
        if self.render_mode is None:
            gymnasium.logger.warn("render() called without a render_mode; pass render_mode='rgb_array'")
            return None
        from racing_env.render import Renderer

        if self._renderer is None:
            self._renderer = Renderer(
                self.track, self.game.vehicles, size=self.config.render_size, camera=self.config.camera
            )
        frame = self._renderer.frame(self._x, self._active, title=f"t = {self._steps * self.config.dt:5.1f} s")
        if self.render_mode == "human":
            self._renderer.show(frame)
            return None
        return frame

    def close(self) -> None:
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None


def parallel_env(**config: Any) -> RacingParallelEnv:
    """Create a ``RacingParallelEnv`` from ``RaceConfig`` keyword arguments."""
    return RacingParallelEnv(RaceConfig(**config))
