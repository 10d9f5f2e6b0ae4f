"""``python -m tools.modbus_export``: one export process (:func:`tools.modbus_export.process.main`)."""

import sys

from tools.modbus_export.process import main

sys.exit(main())
