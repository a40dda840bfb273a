"""Sweeps past one device: a many-worlds sweep split over the GPUs of one machine, or into batches
that run as Ray tasks on a cluster.

What lives here:

- ``devices``: :func:`run_device_sweep`, ``warpsim sweep --devices cuda:0,cuda:1`` (or ``all``,
  or ``cpu,cpu``): contiguous blocks of worlds, one per device, each stepped by its own thread in
  one process; the table, samples and occupancy record equal the one-device sweep byte for byte.

- ``batches``: split a sweep's worlds into batches; each batch is written into its own folder under
  a temporary name and renamed into place only when complete (``publish_batch``), with a SHA-256
  over its files, so a root layer never references a partial batch.
- ``manifest``: :class:`SweepManifest`, the JSON record beside the root of which batches finished
  (checksum, timing, host) and of the sweep they belong to; ``--resume`` skips what it lists.
- ``ray_sweep``: :func:`run_ray_sweep`, the driver (one Ray task per batch, one GPU per task where
  the cluster has GPUs, one CPU otherwise, Ray's task retries for killed workers), and the
  ``--ray`` / ``--batch-size`` / ``--resume`` options of ``warpsim sweep``.
- ``ray_head``: :func:`start_local_head`, the local cluster of ``--ray`` started or refused in one
  line naming the cause and the fix (:class:`RayHeadError`: an address-space limit the raylet's
  object store cannot be mapped under is refused before Ray starts).

It drives no kernels of its own: each task calls ``warpsim.sweeps.run_batch`` (the batched
many-worlds run) and the driver ``warpsim.sweeps.write_sweep_root`` / ``write_table``. Ray (the
optional extra ``warpsim[ray]``) is imported only inside the functions that need it, so
``import warpsim`` never imports it.
"""
