"""The contract between processes: the Bit3 buffer's layout, status bits, sequence lock, buffer, ring and client."""
