"""Entry point of ``python -m ble_groundtruth.deploy``."""

from ble_groundtruth.deploy.cli import main

main()
