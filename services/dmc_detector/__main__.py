"""``python -m services.dmc_detector [--impl threshold|fcm|single|quasistatic] ...``

Every implementation serves the role ``dmc_detector``; ``--impl`` picks one (default threshold).
"""

import sys

from magmesh.runtime import main

from .impls import IMPLEMENTATIONS, pop_impl_arg

if __name__ == "__main__":
    impl, argv = pop_impl_arg(sys.argv[1:])
    main(IMPLEMENTATIONS[impl], argv, IMPLEMENTATIONS)
