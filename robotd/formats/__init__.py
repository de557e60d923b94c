"""The formats layer (docs/architecture.md "Module map"): the bounded queues, the autopilot's field
values, the messages' CBOR, the map file, recordings (MCAP) with their bounded reader and
Foxglove's protobuf schemas. Files and a writer thread; no sockets or processes.
"""
