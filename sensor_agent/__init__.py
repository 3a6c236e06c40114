"""Sensor agent: scans BLE adapters (or replays / simulates them) and publishes RSSI batches over Zenoh."""
