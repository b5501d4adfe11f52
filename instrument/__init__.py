"""instrument: device interfaces, simulated devices, hardware drivers, wire-protocol emulators and rigs."""
