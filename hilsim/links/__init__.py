"""Transports: the only code that touches sockets, ptys, CAN buses and Modbus servers."""
