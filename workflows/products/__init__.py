"""What a user runs: the comparison (``pbmdem compare``), the validation campaign
(``pbmdem validate``) and the design tool (``pbmdem design``)."""
