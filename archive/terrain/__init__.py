"""The ground under the flight: DEMs and the surfaces the rays hit (docs/layout.md)."""
