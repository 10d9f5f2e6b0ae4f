"""Lab tools over the live system: checkout, recording, scope, replay, monitor, Modbus export; tools.cli is the `pfma` command."""
