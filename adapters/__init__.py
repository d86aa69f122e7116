"""Field-protocol adapters: real field devices (PV inverters behind SunSpec Modbus) as devices of the cvvc bus."""
