"""The wheels: quadrature decoding, the encoder source on pigpiod's notifications, and the L298 motor outputs.

Public API: `quadrature.QuadratureDecoder`, `encoders` (PigpioEncoders, WheelTicks, EncoderSource), `motors`
(GpiozeroMotors, MotorOutputs, stop_all_motors).
"""
