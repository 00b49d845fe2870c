"""Fleet: coefficient drift across devices and time (trend, control limits, CUSUM)."""
