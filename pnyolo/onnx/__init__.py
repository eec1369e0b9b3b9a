"""A trained detector as an ONNX graph: ``convention`` (what a caller passes and gets back), ``integrity`` (the
digest and the binding to its checkpoint), ``backend`` (export and ONNX Runtime), ``int8`` (static INT8)."""
