"""The so101-twin AWS stack: network, identity, the DCV twin host, optional auto-stop."""
