"""The update path: from the handlers to the written output — the registry of deformed objects, one
deformer's update (evaluate.py: snapshot → motions → ψ → kernel → shape pass → output), its bind record
and result, the output store and the read-ahead, the frame check and the validation of what it reads."""
