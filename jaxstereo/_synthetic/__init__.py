"""The synthetic flume: scenes, the JAX renderer, rigs, calibration photographs, the demo."""
