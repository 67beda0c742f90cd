"""Work beyond one process, on Ray (``pip install 'mi-gaussians[ray]'``): sweeps of many training runs
(:mod:`.sweep`), and a scene's path-traced references rendered by several workers (:mod:`.references`).

Nothing here imports Ray at import time; :func:`.ray_cluster.import_ray` does, with a one-line error naming the extra
when it is missing. ``ray.init()`` without an address starts a local cluster, so the same command runs on a laptop
and, with ``--address``, on a cluster (whose nodes must see the output folder:
:func:`.ray_cluster.check_shared_folder`).
"""
