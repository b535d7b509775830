"""``python -m magmesh``: the ``magmesh`` command (the operator app lives in :mod:`magmesh_cli`; this entry point
only starts it — nothing in the library imports the app)."""

if __name__ == "__main__":
    from magmesh_cli.cli import run_main

    run_main()
