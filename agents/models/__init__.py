"""Networks and world models: feature encoders and policy heads, the PETS-style ensemble, PlaNet's RSSM and their open-loop check."""
