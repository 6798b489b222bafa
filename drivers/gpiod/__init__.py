"""The Raspberry Pi 5 GPIO back-end: encoders on a libgpiod v2 line request, motors on RP1 hardware PWM and libgpiod."""
