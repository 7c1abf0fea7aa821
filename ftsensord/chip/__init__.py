"""Floor 3, the chip: the MLX90393 and the I2C wire it sits on.

Owns the datasheet's facts in its names (`mlx90393`: opcodes, status byte,
register fields, sensitivity, conversion times, forbidden settings), the
driver of one chip at one address (`driver.MLX90393`), and the wire's facts
and the `Bus` surface every bus offers (`i2c`).

May import: smbus2, numpy, `ftsensord.errors`. Not the model (the chip knows
tesla, not wrenches), nor anything above.
"""
