"""What each command does, between its door in :mod:`resireg_train.cli` and the packages it uses."""
