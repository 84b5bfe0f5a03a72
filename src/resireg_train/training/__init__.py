"""The LightningModule of the 25M VLM and its losses."""
