"""Running the pipeline: options, the cluster, single renders, per-flight batches, tiles and time
stacks (docs/layout.md)."""
