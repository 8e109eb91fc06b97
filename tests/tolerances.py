"""Tolerances used across the tests, in one table."""

FLOAT32_EXACT = 0.0  # bit-identical round trips (float EXR channels)
HALF_RTOL = 1e-3  # float16 round trip: 10-bit mantissa, relative
FILTER_ATOL = 1e-5  # filters on O(1) values that should return their input (constants)
ORT_ATOL = 1e-4  # torch vs ONNX Runtime, float32 convolutions summed in another order, O(1) outputs
TWIN_ATOL = 1e-5  # numpy vs torch twins of the same float32 arithmetic on O(1) values
