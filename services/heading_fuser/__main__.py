"""``python -m services.heading_fuser [--impl ekf|vqf] ...`` (default ekf)."""

import sys

from magmesh.runtime import main

from .impls import DEFAULT_IMPL, IMPLEMENTATIONS, pop_impl_arg  # noqa: F401 - DEFAULT_IMPL: read by the supervisor

if __name__ == "__main__":
    impl, argv = pop_impl_arg(sys.argv[1:])
    main(IMPLEMENTATIONS[impl], argv, IMPLEMENTATIONS)
