"""The sensor board: its frame format (sans-IO decoder), the serial port, the board-clock to host-clock map."""
