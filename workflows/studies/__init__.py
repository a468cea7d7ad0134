"""Research on DEM runs (``pbmdem study ...``): why the transport model is what it is.
They import the product; the product never imports them."""
