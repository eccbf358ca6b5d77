"""Plain ``nn.Module``s: normal CNN, SIREN, sensor models, intersection finder."""
