"""Recording to MCAP: schema, writer, capture, reader."""
