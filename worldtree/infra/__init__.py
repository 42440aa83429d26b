"""Infrastructure of the library: what the model modules use and what knows nothing of the model.

Rule: a module here imports the standard library, third-party packages and other ``worldtree.infra``
modules only, never another part of ``worldtree`` (nor ``methods``, ``nvidia_ls`` or ``benchmarks``);
``tests/test_layering.py`` checks it. Code that needs a model type belongs beside the model instead.

- :mod:`worldtree.infra.errors` -- :class:`~worldtree.infra.errors.UserError`, the one-line error of the CLIs,
  and :class:`~worldtree.infra.errors.SettingError`, one about a setting the library names by its field.
- :mod:`worldtree.infra.cli_runner` -- runs a CLI app: ``UserError`` and Ctrl-C as one line and an exit status;
  a ``SettingError`` names the option that set its field.
- :mod:`worldtree.infra.atomic` -- files and folders written whole or not at all.
- :mod:`worldtree.infra.folder_lock` -- one writer per output folder.
- :mod:`worldtree.infra.output_paths` -- an output path checked before long work.
- :mod:`worldtree.infra.torchfile` -- torch files written atomically, read with ``weights_only=True``.
- :mod:`worldtree.infra.hashing` -- content hashes of manifests and evaluation records.
- :mod:`worldtree.infra.typed_config` -- the walk over a config dataclass's field types (JSON and ``--set``).
- :mod:`worldtree.infra.config_json` -- typed dataclass settings as plain JSON.
- :mod:`worldtree.infra.config_ranges` -- the declared range of every numeric config setting and its check.
- :mod:`worldtree.infra.timing` -- the run's stage clock, kept across resumed sessions.
- :mod:`worldtree.infra.device` -- the compute device picked at run time.
- :mod:`worldtree.infra.cores` -- the CPU cores this process may run on.
- :mod:`worldtree.infra.openmp_policy` -- how OpenMP threads wait between parallel loops (a short spin, then sleep).
- :mod:`worldtree.infra.thread_governor` -- torch's thread count follows the cores other processes leave free.
"""
