"""``robotd replay-many``: many replays (sources × configurations) on local processes or on Ray.

- :mod:`robotd.tools.batch.sources`: what to replay (URLs, files, folders, globs) and each source's
  digest (exact for recordings, cheap for dataset folders);
- :mod:`robotd.tools.batch.configs`: the configurations (config files, ``--set`` and ``--variant``
  overrides) and each one's digest;
- :mod:`robotd.tools.batch.jobs`: one replay, in whatever process runs it (a local worker or a Ray
  task): ``robotd.tools.replay.replay`` in-process, with its time and memory watched;
- :mod:`robotd.tools.batch.store`: the results folder (one JSON line per finished replay, keyed by
  source digest, configuration digest and robotd version; rerunning skips what is done);
- :mod:`robotd.tools.batch.local`: the default engine, one worker process per core;
- :mod:`robotd.tools.batch.ray_engine`: the same jobs as Ray tasks (``pip install 'robotd[cluster]'``);
- :mod:`robotd.tools.batch.table`: the table (Markdown, JSON, CSV) with a comparison per configuration;
- :mod:`robotd.tools.batch.compare`: the regression report between two result sets;
- :mod:`robotd.tools.batch.run`: the command's orchestration.

Nothing here is imported by the daemon. The local default never imports ray. docs/fleet.md.
"""
