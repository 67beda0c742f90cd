"""A scene's path-traced references rendered by Ray workers (``mi-gs optimize scene.xml --workers N``, and the
scene files of a sweep).

:class:`RayFarm` is a farm for :func:`mi_gaussians.data.scene_references.render_references`: ``workers`` Ray actors
each load the scene once, with the run's ``-D`` parameters, and render their share of the missing references (and
exact depths) as they come free. Every reference has its own sampler seed, so the cached files are the same, bit for
bit, as a single-process render's. An actor that dies is restarted (it loads the scene again) and its view retried."""

from __future__ import annotations

from pathlib import Path

from .ray_cluster import import_ray, setup_worker, task_error_line


class _SceneRenderer:
    """A Ray actor: the scene loaded once; renders jobs (``scene_references.ReferenceJob``) one at a time."""

    def __init__(self, path: str, defines: tuple, variant: str):
        setup_worker(variant)
        from ..data.scene_file import load_scene

        self.scene = load_scene(Path(path), defines)

    def render(self, k: int, job, spp: int):
        from ..data.scene_references import render_jobs

        (_, image, depth), = render_jobs(self.scene, [job], spp)
        return k, image, depth


class RayFarm:
    """Renders a scene's reference jobs on ``workers`` Ray actors of the connected cluster (``ray.init`` first,
    e.g. :func:`.ray_cluster.connected`); ``cpus`` per actor (Dr.Jit's threads in it)."""

    def __init__(self, path: str | Path, defines, variant: str, workers: int, cpus: float = 1.0):
        self.path, self.defines, self.variant = str(Path(path).resolve()), tuple(defines or ()), variant
        self.workers, self.cpus = int(workers), float(cpus)

    def describe(self) -> str:
        return f"{self.workers} Ray worker{'s' if self.workers != 1 else ''}"

    def render(self, jobs: list, spp: int):
        """Yield (job index, reference or None, depth or None) for each job, in the order they finish."""
        if not jobs:
            return
        ray = import_ray()
        from ray.util import ActorPool

        actor = ray.remote(num_cpus=self.cpus, max_restarts=2, max_task_retries=2)(_SceneRenderer)
        actors = [actor.remote(self.path, self.defines, self.variant) for _ in range(min(self.workers, len(jobs)))]
        try:
            pool = ActorPool(actors)
            yield from pool.map_unordered(lambda a, kj: a.render.remote(kj[0], kj[1], spp), list(enumerate(jobs)))
        except ray.exceptions.RayTaskError as e:        # (the scene failed in a worker: its own one-line error)
            raise ValueError(task_error_line(e)) from None
        except ray.exceptions.RayActorError:
            raise ValueError(f"{self.path}: a worker rendering its references died, and again when restarted") \
                from None
        finally:
            for a in actors:
                ray.kill(a)
