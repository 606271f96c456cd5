"""The univariate nonstationary growth model (``examples.ungm.system:UNGM``)."""
