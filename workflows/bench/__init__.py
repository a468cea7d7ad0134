"""The benchmarks (``pbmdem bench ...``): speed, accuracy and cost of every stage. They
import the product; the product never imports them."""
