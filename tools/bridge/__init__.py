"""The Bit3 areas over Zenoh (issue 19, docs/bridge.md): :mod:`.session` opens a peer
session on explicit endpoints, :mod:`.bridge` publishes a local buffer's areas and takes
the command area back from one remote writer, :mod:`.remote` is the far side's client."""
